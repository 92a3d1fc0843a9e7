"""Score simulated proposals as NAVSIM's `PDMScorer` does, for evaluation and for PDM-Closed
(docs/engine.md, "Metrics").

In evaluation proposal 0 is the re-simulated PDM-Closed reference and proposal 1 the submission;
PDM-Closed scores its 15 proposals against its own forecast observation with the planner config. A
metric version is data (`ScorerConfig`): DDC is a multiplier or a weighted row (`ddc_role`) and its
window runs over time or over proposals (`ddc_window_axis`).
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt

from scorer.drivable_map import DrivableMap, MapBatch
from scorer.geometry import FloatArray
from scorer.metrics.aggregation import aggregate
from scorer.metrics.collisions import no_at_fault_collisions
from scorer.metrics.comfort import comfort_series, is_comfortable
from scorer.metrics.drivable_area import drivable_area_compliance
from scorer.metrics.driving_direction import driving_direction_compliance, off_route_steps
from scorer.metrics.ego_areas import ego_areas
from scorer.metrics.ego_box import ego_box_points
from scorer.metrics.progress import centerline_strings, normalized_progress, raw_progress
from scorer.metrics.time_to_collision import time_to_collision
from scorer.observation import Observation, ObservationBatch
from scorer.trajectory import SCORING_INTERVAL_S, SCORING_POSES, STATE_SIZE
from scorer.versions import ScorerConfig

IntArray = npt.NDArray[np.intp]


@dataclass(frozen=True, eq=False)
class ProposalScores:
    """Per-proposal results, (P,) for one token or (B, P) for a batch: the devkit's result columns, raw
    progress, infraction indices and its metric rows."""

    no_at_fault_collisions: FloatArray
    drivable_area_compliance: FloatArray
    driving_direction_compliance: FloatArray
    ego_progress: FloatArray  # normalised
    time_to_collision_within_bound: FloatArray
    comfort: FloatArray  # 1.0 or 0.0
    score: FloatArray
    progress_raw: FloatArray  # m, before multipliers
    collision_index: IntArray  # first at-fault collision, time index (time = index * 0.1 s); -1 if none
    collision_object: IntArray  # the object of that collision, its index in the token's observation; -1
    ttc_index: IntArray  # first TTC infraction, likewise
    ttc_object: IntArray
    ego_areas: npt.NDArray[np.bool_]  # (..., 41, 3) MULTIPLE_LANES, NON_DRIVABLE_AREA, ONCOMING_TRAFFIC
    multiplier_rows: dict[str, FloatArray]  # the devkit's multi-metric rows, by its names, in order
    weighted_rows: dict[str, FloatArray]  # its weighted-metric rows, by its names, in order

    def token(self, index: int) -> ProposalScores:
        """Return the (P,) results of token `index` of a batch."""
        values = {field.name: getattr(self, field.name) for field in fields(self)}
        row_of_token: dict[str, Any] = {
            name: {row: array[index] for row, array in value.items()}
            if isinstance(value, dict)
            else value[index]
            for name, value in values.items()
        }
        return ProposalScores(**row_of_token)

    def subscores(self, proposal: int) -> dict[str, float]:
        """Return one proposal's rows and score under the devkit's names (e.g. `pdm_closed_subscores`)."""
        rows = {**self.multiplier_rows, **self.weighted_rows}
        return {name: float(row[proposal]) for name, row in rows.items()} | {
            "score": float(self.score[proposal])
        }


@dataclass(frozen=True, eq=False)
class ProposalMeasures:
    """What each proposal earns on its own, (B, P) arrays: all but the steps that compare proposals (the
    v1.0 DDC window, EP normalisation, comfort's filters, aggregation). A proposal's measures do not depend
    on the others it is scored with, so a reference proposal can be measured once and joined with others
    later.
    """

    no_at_fault_collisions: FloatArray
    collision_index: IntArray
    collision_object: IntArray  # index in the token's observation; -1 without a collision
    drivable_area_compliance: FloatArray
    time_to_collision_within_bound: FloatArray
    ttc_index: IntArray
    ttc_object: IntArray
    comfort_series: FloatArray  # (B, P, 41, 3): comfort is scored on a token's proposals together
    progress_raw: FloatArray
    off_route_steps: FloatArray  # (B, P, 41) centre displacement per step while off route
    ego_areas: npt.NDArray[np.bool_]  # (B, P, 41, 3)

    def token(self, index: int) -> ProposalMeasures:
        """Return the measures of token `index` as a batch of one (1, P)."""
        return ProposalMeasures(
            **{field.name: getattr(self, field.name)[index : index + 1] for field in fields(self)}
        )


def join_measures(parts: Sequence[ProposalMeasures], axis: int = 1) -> ProposalMeasures:
    """Return the measures of `parts` side by side: as more proposals (axis 1) or more tokens (axis 0)."""
    return ProposalMeasures(
        **{
            field.name: np.concatenate([getattr(part, field.name) for part in parts], axis=axis)
            for field in fields(ProposalMeasures)
        }
    )


def score_proposals(
    states: FloatArray,
    observation: Observation,
    drivable_map: DrivableMap,
    centerline_xy: FloatArray,
    route_lane_ids: Collection[str],
    config: ScorerConfig,
) -> ProposalScores:
    """Return the scores of simulated proposals (P, 41, 11) against an observation and map.

    See docs/engine.md, "Metrics".
    """
    states = np.asarray(states, dtype=np.float64)
    return score_batch(
        states[None], [observation], [drivable_map], [centerline_xy], [route_lane_ids], config
    ).token(0)


def score_batch(
    states: FloatArray,
    observations: Sequence[Observation],
    drivable_maps: Sequence[DrivableMap],
    centerlines: Sequence[FloatArray],
    route_lane_ids: Sequence[Collection[str]],
    config: ScorerConfig,
) -> ProposalScores:
    """Return the scores (B, P) of B tokens' simulated proposals (B, P, 41, 11), each against its own inputs.

    Every token is scored as if alone (`score_proposals`); the batch only shares the array calls.
    """
    return score_measures(
        measure_batch(states, observations, drivable_maps, centerlines, route_lane_ids, config), config
    )


def measure_batch(
    states: FloatArray,
    observations: Sequence[Observation],
    drivable_maps: Sequence[DrivableMap],
    centerlines: Sequence[FloatArray],
    route_lane_ids: Sequence[Collection[str]],
    config: ScorerConfig,
) -> ProposalMeasures:
    """Return the per-proposal measures (B, P) of B tokens' simulated proposals (B, P, 41, 11)."""
    states = np.asarray(states, dtype=np.float64)
    if states.ndim != 4 or states.shape[2:] != (SCORING_POSES + 1, STATE_SIZE):
        raise ValueError(
            f"states: expected shape (B, P, {SCORING_POSES + 1}, {STATE_SIZE}), got {states.shape}"
        )
    num_tokens, num_proposals = states.shape[:2]
    rows = states.reshape(-1, *states.shape[2:])
    row_token = np.repeat(np.arange(num_tokens), num_proposals)
    batch_observations = ObservationBatch.of(observations)
    maps = MapBatch.of(drivable_maps, route_lane_ids)

    def per_token(values: np.ndarray) -> np.ndarray:
        return values.reshape(num_tokens, num_proposals, *values.shape[1:])

    def local_object(batch_column: IntArray) -> IntArray:
        """Return object columns of the batch as indices in each row's own observation (-1 stays -1)."""
        return np.where(batch_column >= 0, batch_column - batch_observations.start[row_token], -1)

    points = ego_box_points(rows)
    areas = ego_areas(points, row_token, maps)
    collisions, collision = no_at_fault_collisions(rows, points, areas, row_token, batch_observations)
    ttc, ttc_infraction = time_to_collision(
        rows,
        points,
        areas,
        row_token,
        batch_observations,
        maps,
        config.stopped_speed_threshold,
        SCORING_INTERVAL_S,
    )
    return ProposalMeasures(
        no_at_fault_collisions=per_token(collisions),
        collision_index=per_token(collision.index),
        collision_object=per_token(local_object(collision.obj)),
        drivable_area_compliance=per_token(drivable_area_compliance(areas)),
        time_to_collision_within_bound=per_token(ttc),
        ttc_index=per_token(ttc_infraction.index),
        ttc_object=per_token(local_object(ttc_infraction.obj)),
        comfort_series=per_token(comfort_series(rows)),
        progress_raw=per_token(raw_progress(points, centerline_strings(list(centerlines)), row_token)),
        off_route_steps=per_token(off_route_steps(points, areas)),
        ego_areas=per_token(areas),
    )


def score_measures(measures: ProposalMeasures, config: ScorerConfig) -> ProposalScores:
    """Return the scores (B, P) from the proposals' measures: DDC windows, EP normalisation, comfort,
    aggregation: the steps in which the devkit's result for a proposal depends on the others."""
    comfort = is_comfortable(measures.comfort_series, SCORING_INTERVAL_S).astype(np.float64)
    driving_direction = driving_direction_compliance(measures.off_route_steps, config, SCORING_INTERVAL_S)
    # DDC is a multiplier (v1.0) or a weighted row (v1.1, weight 0): data, not a version test.
    ddc_is_multiplier = config.ddc_role == "multiplier"
    ddc_row = {"driving_direction": driving_direction}
    multiplier_rows = {
        "no_collision": measures.no_at_fault_collisions,
        "drivable_area": measures.drivable_area_compliance,
    } | (ddc_row if ddc_is_multiplier else {})
    multipliers = np.stack(list(multiplier_rows.values()))
    ego_progress = normalized_progress(
        measures.progress_raw, multipliers.prod(axis=0), config.progress_distance_threshold
    )
    weighted_rows = {
        "progress": ego_progress,
        "ttc": measures.time_to_collision_within_bound,
        "comfortable": comfort,
    } | ({} if ddc_is_multiplier else ddc_row)
    weights = [config.progress_weight, config.ttc_weight, config.comfortable_weight]
    weights += [] if ddc_is_multiplier else [config.driving_direction_weight]
    score = aggregate(multipliers, np.stack(list(weighted_rows.values())), np.array(weights))

    return ProposalScores(
        no_at_fault_collisions=measures.no_at_fault_collisions,
        drivable_area_compliance=measures.drivable_area_compliance,
        driving_direction_compliance=driving_direction,
        ego_progress=ego_progress,
        time_to_collision_within_bound=measures.time_to_collision_within_bound,
        comfort=comfort,
        score=score,
        progress_raw=measures.progress_raw,
        collision_index=measures.collision_index,
        collision_object=measures.collision_object,
        ttc_index=measures.ttc_index,
        ttc_object=measures.ttc_object,
        ego_areas=measures.ego_areas,
        multiplier_rows=multiplier_rows,
        weighted_rows=weighted_rows,
    )
