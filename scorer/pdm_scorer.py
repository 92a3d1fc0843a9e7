"""Score simulated proposals as NAVSIM's `PDMScorer` does, for evaluation and for PDM-Closed
(docs/engine.md, "Metrics").

In evaluation proposal 0 is the re-simulated PDM-Closed reference and proposal 1 the submission;
PDM-Closed scores its 15 proposals against its own forecast observation with the planner config. A
metric version is data (`ScorerConfig`): its multiplier and weighted rows, by the devkit's names, decide
which metrics count and how (DDC a multiplier in v1.0 and v2, a row of weight 0 in v1.1; TLC and LK only
in v2), and a few fields hold the structural choices that changed between releases. Result columns a
version does not score are 1.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, fields
from functools import cache
from typing import Any

import numpy as np
import numpy.typing as npt

from scorer.drivable_map import DrivableMap, MapBatch
from scorer.geometry import BoolArray, FloatArray, IntArray
from scorer.metrics.aggregation import aggregate
from scorer.metrics.collisions import no_at_fault_collisions
from scorer.metrics.comfort import comfort_series, is_comfortable
from scorer.metrics.contacts import FirstInfraction
from scorer.metrics.drivable_area import drivable_area_compliance
from scorer.metrics.driving_direction import driving_direction_compliance, off_route_steps
from scorer.metrics.ego_areas import ego_areas, in_intersection
from scorer.metrics.ego_box import BoxPoint, ego_box_points, ego_corners
from scorer.metrics.history_comfort import history_comfort
from scorer.metrics.lane_keeping import lane_keeping
from scorer.metrics.progress import centerline_strings, normalised_progress, raw_progress
from scorer.metrics.time_to_collision import time_to_collision
from scorer.metrics.traffic_light import traffic_light_compliance
from scorer.observation import Observation, ObservationBatch
from scorer.trajectory import SCORING_INTERVAL_S, SCORING_POSES, STATE_SIZE
from scorer.versions import ScorerConfig

# The devkit's metric rows (`MultiMetricIndex`, `WeightedMetricIndex` names) and the result column of each.
RESULT_COLUMN_OF_ROW = {
    "no_collision": "no_at_fault_collisions",
    "drivable_area": "drivable_area_compliance",
    "traffic_light_compliance": "traffic_light_compliance",
    "driving_direction": "driving_direction_compliance",
    "progress": "ego_progress",
    "ttc": "time_to_collision_within_bound",
    "comfortable": "comfort",
    "lane_keeping": "lane_keeping",
    "history_comfort": "history_comfort",
}


@dataclass(frozen=True, eq=False)
class ProposalScores:
    """Per-proposal results, (P,) for one token or (B, P) for a batch: the devkit's result columns, raw
    progress, infraction indices and its metric rows."""

    no_at_fault_collisions: FloatArray
    drivable_area_compliance: FloatArray
    driving_direction_compliance: FloatArray
    ego_progress: FloatArray  # normalised
    time_to_collision_within_bound: FloatArray
    comfort: FloatArray  # 1.0 or 0.0 (v1)
    traffic_light_compliance: FloatArray  # v2
    lane_keeping: FloatArray  # v2
    history_comfort: FloatArray  # v2
    score: FloatArray
    progress_raw: FloatArray  # m, before multipliers
    collision_index: IntArray  # first at-fault collision, time index (time = index * 0.1 s); -1 if none
    collision_object: IntArray  # the object of that collision, its index in the token's observation; -1
    ttc_index: IntArray  # first TTC infraction, likewise
    ttc_object: IntArray
    red_light_index: IntArray  # first red-light contact, likewise
    red_light: IntArray  # that light, its index in the token's red lights; -1
    lane_keeping_index: IntArray  # the time index at which the run beyond the limit reached the window
    lane_keeping_run: IntArray  # the longest run of time indices beyond the limit
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
    comfort_series: FloatArray  # (B, P, n, c): comfort is scored on a token's proposals together
    progress_raw: FloatArray
    off_route_steps: FloatArray  # (B, P, 41) centre displacement per step while off route
    ego_areas: npt.NDArray[np.bool_]  # (B, P, 41, 3)
    traffic_light_compliance: FloatArray  # 1 where the version has no TLC
    red_light_index: IntArray
    red_light: IntArray
    lane_keeping: FloatArray  # 1 where the version has no LK
    lane_keeping_index: IntArray
    lane_keeping_run: IntArray

    def token(self, index: int) -> ProposalMeasures:
        """Return the measures of token `index` as a batch of one (1, P)."""
        return ProposalMeasures(
            **{field.name: getattr(self, field.name)[index : index + 1] for field in fields(self)}
        )


@dataclass(frozen=True)
class MeasureSettings:
    """What `measure_batch` reads of a `ScorerConfig`: configs that agree here measure proposals alike and
    differ only in `score_measures`, so they can share one measurement (PDM-Closed's planner configs of v1.0
    and v1.1 do)."""

    stopped_speed_threshold: float
    ttc_evaluated_steps: int
    ddc_excludes_intersections: bool
    traffic_light_compliance: bool
    lane_keeping: tuple[float, float] | None  # deviation limit (m) and horizon window (s); None without LK
    comfort_at_centre: bool  # v2's history comfort reads the longitudinal acceleration at the centre

    @classmethod
    def of(cls, config: ScorerConfig) -> MeasureSettings:
        """Return what `config` sets of the measures."""
        uses = set(config.multiplier_rows) | set(config.weights)
        return cls(
            stopped_speed_threshold=config.stopped_speed_threshold,
            ttc_evaluated_steps=config.ttc_evaluated_steps,
            ddc_excludes_intersections=config.ddc_excludes_intersections,
            traffic_light_compliance="traffic_light_compliance" in uses,
            lane_keeping=(
                (config.lane_keeping_deviation_limit, config.lane_keeping_horizon_window)
                if "lane_keeping" in uses
                else None
            ),
            comfort_at_centre="history_comfort" in uses,
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
    """Return the per-proposal measures (B, P) of B tokens' simulated proposals (B, P, 41, 11); of `config`,
    only its `MeasureSettings` count."""
    inputs = ([observations], drivable_maps, centerlines, route_lane_ids)
    return measure_alike(states, *inputs, [MeasureSettings.of(config)])[0]


class _Observed:
    """What one observation (per token) decides of a batch's measures: the batch of its objects and NC."""

    def __init__(
        self,
        observations: Sequence[Observation],
        rows: FloatArray,
        points: FloatArray,
        areas: BoolArray,
        row_token: IntArray,
    ) -> None:
        self.batch = ObservationBatch.of(observations)
        self.row_token = row_token
        self.collisions, self.collision = no_at_fault_collisions(rows, points, areas, row_token, self.batch)

    def local_object(self, batch_column: IntArray) -> IntArray:
        """Return object columns of the batch as indices in each row's own observation (-1 stays -1)."""
        return np.where(batch_column >= 0, batch_column - self.batch.start[self.row_token], -1)


def measure_alike(
    states: FloatArray,
    observations: Sequence[Sequence[Observation]],
    drivable_maps: Sequence[DrivableMap],
    centerlines: Sequence[FloatArray],
    route_lane_ids: Sequence[Collection[str]],
    settings: Sequence[MeasureSettings],
) -> list[ProposalMeasures]:
    """Return the per-proposal measures (B, P) of B tokens' simulated proposals (B, P, 41, 11) under each of
    `settings`, `observations[k]` (one per token) being what `settings[k]` observes; each as measured alone.

    What reads the map and the ego alone (the ego boxes, their areas, DAC, progress) is measured once; what
    reads the observation too (NC, TTC, TLC) once per observation (settings given the same Observation objects
    share it); every other measure once per value of the settings it reads.
    """
    states = np.asarray(states, dtype=np.float64)
    if states.ndim != 4 or states.shape[2:] != (SCORING_POSES + 1, STATE_SIZE):
        raise ValueError(
            f"states: expected shape (B, P, {SCORING_POSES + 1}, {STATE_SIZE}), got {states.shape}"
        )
    num_tokens, num_proposals = states.shape[:2]
    rows = states.reshape(-1, *states.shape[2:])
    row_token = np.repeat(np.arange(num_tokens), num_proposals)
    maps = MapBatch.of(drivable_maps, route_lane_ids)

    def per_token(values: np.ndarray) -> np.ndarray:
        return values.reshape(num_tokens, num_proposals, *values.shape[1:])

    points = ego_box_points(rows)
    areas = ego_areas(points, row_token, maps)
    centers = points[..., BoxPoint.CENTER, :]
    num_steps = rows.shape[1]
    centerline_lines = centerline_strings(list(centerlines))
    no_index = np.full(len(rows), -1, dtype=np.intp)

    # An observation is named by its Observation objects: settings given the same objects share its measures.
    observation_keys = [tuple(map(id, token_observations)) for token_observations in observations]
    observation_of = dict(zip(observation_keys, observations, strict=True))

    @cache
    def observed(key: tuple[int, ...]) -> _Observed:
        return _Observed(observation_of[key], rows, points, areas, row_token)

    @cache
    def ttc(
        key: tuple[int, ...], stopped_speed_threshold: float
    ) -> dict[int, tuple[FloatArray, FirstInfraction]]:
        # The horizons of the settings reading this observation only: another may hold fewer time steps.
        reading = zip(settings, observation_keys, strict=True)
        horizons = sorted({setting.ttc_evaluated_steps for setting, seen in reading if seen == key})
        measured = time_to_collision(
            rows,
            points,
            areas,
            row_token,
            observed(key).batch,
            maps,
            stopped_speed_threshold,
            SCORING_INTERVAL_S,
            horizons,
        )
        return dict(zip(horizons, measured, strict=True))

    @cache
    def centre_in_intersection() -> BoolArray:
        return in_intersection(
            centers[..., 0].reshape(-1), centers[..., 1].reshape(-1), np.repeat(row_token, num_steps), maps
        ).reshape(len(rows), num_steps)

    @cache
    def traffic_light(key: tuple[int, ...]) -> tuple[FloatArray, IntArray, IntArray]:
        red_lights = [observation.red_lights for observation in observation_of[key]]
        return traffic_light_compliance(ego_corners(points), row_token, red_lights)

    @cache
    def keeping(limits: tuple[float, float]) -> tuple[FloatArray, IntArray, IntArray]:
        inside = centre_in_intersection()
        return lane_keeping(centers, inside, centerline_lines, row_token, *limits, SCORING_INTERVAL_S)

    @cache
    def comfort(at_centre: bool) -> FloatArray:
        return per_token(comfort_series(rows, at_centre=at_centre))

    @cache
    def off_route(excludes_intersections: bool) -> FloatArray:
        excluded = centre_in_intersection() if excludes_intersections else None
        return per_token(off_route_steps(points, areas, excluded))

    shared = {
        "drivable_area_compliance": per_token(drivable_area_compliance(areas)),
        "progress_raw": per_token(raw_progress(points, centerline_lines, row_token)),
        "ego_areas": per_token(areas),
    }
    measures = []
    for setting, key in zip(settings, observation_keys, strict=True):
        seen = observed(key)
        time_to_collision_within_bound, ttc_infraction = ttc(key, setting.stopped_speed_threshold)[
            setting.ttc_evaluated_steps
        ]
        light: tuple[FloatArray, IntArray, IntArray] = (np.ones(len(rows)), no_index, no_index)
        if setting.traffic_light_compliance:
            light = traffic_light(key)
        lane: tuple[FloatArray, IntArray, IntArray] = (
            np.ones(len(rows)),
            no_index,
            np.zeros(len(rows), dtype=np.intp),
        )
        if setting.lane_keeping is not None:
            lane = keeping(setting.lane_keeping)
        measures.append(
            ProposalMeasures(
                **shared,
                no_at_fault_collisions=per_token(seen.collisions),
                collision_index=per_token(seen.collision.index),
                collision_object=per_token(seen.local_object(seen.collision.obj)),
                time_to_collision_within_bound=per_token(time_to_collision_within_bound),
                ttc_index=per_token(ttc_infraction.index),
                ttc_object=per_token(seen.local_object(ttc_infraction.obj)),
                comfort_series=comfort(setting.comfort_at_centre),
                off_route_steps=off_route(setting.ddc_excludes_intersections),
                traffic_light_compliance=per_token(light[0]),
                red_light_index=per_token(light[1]),
                red_light=per_token(light[2]),
                lane_keeping=per_token(lane[0]),
                lane_keeping_index=per_token(lane[1]),
                lane_keeping_run=per_token(lane[2]),
            )
        )
    return measures


def score_measures(
    measures: ProposalMeasures, config: ScorerConfig, pasts: Sequence[FloatArray | None] | None = None
) -> ProposalScores:
    """Return the scores (B, P) from the proposals' measures: DDC windows, EP normalisation, comfort,
    aggregation: the steps in which the devkit's result for a proposal depends on the others.

    `pasts` are each token's past ego states (`history_comfort.past_states`) for v2's history comfort;
    without them (PDM-Closed's own ranking, the human of the filter) the devkit leaves HC at 1.
    """
    ones = np.ones_like(measures.progress_raw)
    weights = config.weights
    comfort = ones
    if "comfortable" in weights:
        comfort = is_comfortable(measures.comfort_series, SCORING_INTERVAL_S).astype(np.float64)
    with_history = ones
    if "history_comfort" in weights and pasts is not None:
        with_history = history_comfort(measures.comfort_series, pasts)
    driving_direction = driving_direction_compliance(measures.off_route_steps, config, SCORING_INTERVAL_S)
    columns = {
        "no_at_fault_collisions": measures.no_at_fault_collisions,
        "drivable_area_compliance": measures.drivable_area_compliance,
        "traffic_light_compliance": measures.traffic_light_compliance,
        "driving_direction_compliance": driving_direction,
        "time_to_collision_within_bound": measures.time_to_collision_within_bound,
        "comfort": comfort,
        "lane_keeping": measures.lane_keeping,
        "history_comfort": with_history,
    }
    multiplier_rows = {row: columns[RESULT_COLUMN_OF_ROW[row]] for row in config.multiplier_rows}
    multipliers = np.stack(list(multiplier_rows.values()))
    columns["ego_progress"] = normalised_progress(
        measures.progress_raw,
        multipliers.prod(axis=0),
        config.progress_distance_threshold,
        config.progress_normalisation,
    )
    weighted_rows = {row: columns[RESULT_COLUMN_OF_ROW[row]] for row in weights}
    score = aggregate(multipliers, np.stack(list(weighted_rows.values())), np.array(list(weights.values())))

    return ProposalScores(
        **columns,
        score=score,
        progress_raw=measures.progress_raw,
        collision_index=measures.collision_index,
        collision_object=measures.collision_object,
        ttc_index=measures.ttc_index,
        ttc_object=measures.ttc_object,
        red_light_index=measures.red_light_index,
        red_light=measures.red_light,
        lane_keeping_index=measures.lane_keeping_index,
        lane_keeping_run=measures.lane_keeping_run,
        ego_areas=measures.ego_areas,
        multiplier_rows=multiplier_rows,
        weighted_rows=weighted_rows,
    )
