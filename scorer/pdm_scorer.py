"""Score simulated proposals as NAVSIM's `PDMScorer` does, for evaluation and for PDM-Closed
(docs/engine.md, "Metrics").

In evaluation proposal 0 is the re-simulated PDM-Closed reference and proposal 1 the submission;
PDM-Closed scores its 15 proposals against its own forecast observation with the planner config. A
metric version is data (`ScorerConfig`): its multiplier and weighted rows, by the devkit's names, decide
which metrics count and how (DDC a multiplier in v1.0 and v2, a row of weight 0 in v1.1; TLC and LK only
in v2), and a few fields hold the structural choices that changed between releases. Result columns a
version does not score are 1.
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
from collections.abc import Callable, Collection, Mapping, Sequence
from functools import cache
from typing import Any, NamedTuple

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
from scorer.metrics.pairs import corner_bounds
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


class ProposalScores(NamedTuple):
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

    def token(self, index: int) -> "ProposalScores":
        """Return the (P,) results of token `index` of a batch."""
        values = self._asdict()
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


class ProposalMeasures(NamedTuple):
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

    def token(self, index: int) -> "ProposalMeasures":
        """Return the measures of token `index` as a batch of one (1, P)."""
        return ProposalMeasures(**{name: value[index : index + 1] for name, value in self._asdict().items()})

    def proposal(self, index: int) -> "ProposalMeasures":
        """Return the measures of every token's proposal `index` as proposals of their own (B, 1)."""
        return ProposalMeasures(
            **{name: value[:, index : index + 1] for name, value in self._asdict().items()}
        )


class MeasureSettings(NamedTuple):
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
    def of(cls, config: ScorerConfig) -> "MeasureSettings":
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
            name: np.concatenate([getattr(part, name) for part in parts], axis=axis)
            for name in ProposalMeasures._fields
        }
    )


def score_batch(
    states: FloatArray,
    observations: Sequence[Observation],
    drivable_maps: Sequence[DrivableMap],
    centerlines: Sequence[FloatArray],
    route_lane_ids: Sequence[Collection[str]],
    config: ScorerConfig,
) -> ProposalScores:
    """Return the scores (B, P) of B tokens' simulated proposals (B, P, 41, 11), each against its own inputs.

    Every token is scored as if alone (a batch of one, as the devkit scores it); the batch only shares the
    array calls.
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


# An observation, named by the ids of its Observation objects (one per token).
ObservationKey = tuple[int, ...]
# TLC (R,), each row's first red-light contact: its time index and the light (`traffic_light_compliance`).
TrafficLights = tuple[FloatArray, IntArray, IntArray]
# LK (R,), the time index at which the run beyond the limit reached the window, its longest run.
LaneKeeping = tuple[FloatArray, IntArray, IntArray]


class EgoRows(NamedTuple):
    """B tokens' simulated proposals (B, P, 41, 11) as rows (R = B·P), and what reads only them and the maps
    (the ego's box points, the map areas they lie in): every setting and every observation shares these."""

    rows: FloatArray  # (R, 41, 11)
    row_token: IntArray  # (R,) the token of each row
    num_tokens: int
    num_proposals: int
    maps: MapBatch
    centerlines: npt.NDArray[np.object_]  # (B,) LineStrings
    points: FloatArray  # (R, 41, 5, 2) `ego_box_points`
    bounds: (
        FloatArray  # (R, 41, 4) each box's bounding box (`corner_bounds`): every pruning of pairs starts here
    )
    areas: BoolArray  # (R, 41, 3) `ego_areas`

    @classmethod
    def of(
        cls,
        states: FloatArray,
        drivable_maps: Sequence[DrivableMap],
        centerlines: Sequence[FloatArray],
        route_lane_ids: Sequence[Collection[str]],
    ) -> "EgoRows":
        """Return the rows of `states` (B, P, 41, 11), each token with its map, centerline and route."""
        states = np.asarray(states, dtype=np.float64)
        if states.ndim != 4 or states.shape[2:] != (SCORING_POSES + 1, STATE_SIZE):
            raise ValueError(
                f"states: expected shape (B, P, {SCORING_POSES + 1}, {STATE_SIZE}), got {states.shape}"
            )
        num_tokens, num_proposals = states.shape[:2]
        rows = states.reshape(-1, *states.shape[2:])
        row_token = np.repeat(np.arange(num_tokens), num_proposals)
        maps = MapBatch.of(drivable_maps, route_lane_ids)
        points = ego_box_points(rows)
        bounds = corner_bounds(points)
        return cls(
            rows=rows,
            row_token=row_token,
            num_tokens=num_tokens,
            num_proposals=num_proposals,
            maps=maps,
            centerlines=centerline_strings(list(centerlines)),
            points=points,
            bounds=bounds,
            areas=ego_areas(points, bounds, row_token, maps),
        )

    def per_token(self, values: np.ndarray) -> np.ndarray:
        """Return per-row values (R, ...) as per-token ones (B, P, ...)."""
        return values.reshape(self.num_tokens, self.num_proposals, *values.shape[1:])

    @property
    def centers(self) -> FloatArray:
        """The box centres (R, 41, 2)."""
        return self.points[..., BoxPoint.CENTER, :]


def centre_in_intersection(ego: EgoRows) -> BoolArray:
    """Return whether each box centre is inside an intersection of its token's map (R, 41)."""
    num_rows, num_steps = ego.rows.shape[:2]
    x, y = ego.centers[..., 0].reshape(-1), ego.centers[..., 1].reshape(-1)
    return in_intersection(x, y, np.repeat(ego.row_token, num_steps), ego.maps).reshape(num_rows, num_steps)


class _Observed:
    """What one observation (per token) decides of a batch's measures: the batch of its objects and NC."""

    def __init__(self, observations: Sequence[Observation], ego: EgoRows) -> None:
        self.observations = observations
        self.batch = ObservationBatch.of(observations)
        self.row_token = ego.row_token
        self.collisions, self.collision = no_at_fault_collisions(
            ego.rows, ego.points, ego.bounds, ego.areas, ego.row_token, self.batch
        )

    def local_object(self, batch_column: IntArray) -> IntArray:
        """Return object columns of the batch as indices in each row's own observation (-1 stays -1)."""
        return np.where(batch_column >= 0, batch_column - self.batch.start[self.row_token], -1)


def ttc_horizons(
    readers: Sequence[tuple[MeasureSettings, ObservationKey]],
) -> dict[ObservationKey, list[int]]:
    """Return, per observation, the TTC horizons (time steps) of the settings reading it, in increasing order.

    One contact search over the longest serves them all (`time_to_collision`). Only the horizons of the
    settings reading that observation count: another observation's may be longer than this one holds.
    """
    horizons: dict[ObservationKey, set[int]] = {}
    for setting, key in readers:
        horizons.setdefault(key, set()).add(setting.ttc_evaluated_steps)
    return {key: sorted(steps) for key, steps in horizons.items()}


def _time_to_collision(
    ego: EgoRows,
    observed: Mapping[ObservationKey, _Observed],
    readers: Sequence[tuple[MeasureSettings, ObservationKey]],
) -> dict[tuple[ObservationKey, float, int], tuple[FloatArray, FirstInfraction]]:
    """Return TTC (R,) and its first infractions by (observation, stopped-speed threshold, horizon), measured
    once per observation and threshold that a setting reads, over every horizon read of that observation."""
    horizons = ttc_horizons(readers)
    measured: dict[tuple[ObservationKey, float, int], tuple[FloatArray, FirstInfraction]] = {}
    for key, threshold in dict.fromkeys((key, setting.stopped_speed_threshold) for setting, key in readers):
        batch = observed[key].batch
        found = time_to_collision(
            ego.rows,
            ego.points,
            ego.bounds,
            ego.areas,
            ego.row_token,
            batch,
            ego.maps,
            threshold,
            SCORING_INTERVAL_S,
            horizons[key],
        )
        measured |= {(key, threshold, steps): ttc for steps, ttc in zip(horizons[key], found, strict=True)}
    return measured


def _traffic_lights(
    ego: EgoRows,
    observed: Mapping[ObservationKey, _Observed],
    readers: Sequence[tuple[MeasureSettings, ObservationKey]],
) -> dict[ObservationKey, TrafficLights]:
    """Return TLC by observation, measured for each observation that a setting with TLC reads."""
    reading = dict.fromkeys(key for setting, key in readers if setting.traffic_light_compliance)
    return {
        key: traffic_light_compliance(
            ego_corners(ego.points),
            ego.bounds,
            ego.row_token,
            [observation.red_lights for observation in observed[key].observations],
        )
        for key in reading
    }


def _lane_keeping(
    ego: EgoRows, settings: Sequence[MeasureSettings], centres_inside: Callable[[], BoolArray]
) -> dict[tuple[float, float], LaneKeeping]:
    """Return LK by (deviation limit, horizon window), measured once for each pair a setting reads."""
    limits = dict.fromkeys(setting.lane_keeping for setting in settings if setting.lane_keeping is not None)
    return {
        (limit, window): lane_keeping(
            ego.centers,
            centres_inside(),
            ego.centerlines,
            ego.row_token,
            limit,
            window,
            SCORING_INTERVAL_S,
        )
        for limit, window in limits
    }


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
    ego = EgoRows.of(states, drivable_maps, centerlines, route_lane_ids)
    # An observation is named by its Observation objects: settings given the same objects share its measures.
    keys = [tuple(map(id, token_observations)) for token_observations in observations]
    observed = {key: _Observed(seen, ego) for key, seen in dict(zip(keys, observations, strict=True)).items()}
    readers = list(zip(settings, keys, strict=True))
    ttc = _time_to_collision(ego, observed, readers)
    lights = _traffic_lights(ego, observed, readers)

    # v2's DDC and LK read which box centres are inside an intersection: found once, where a setting reads it.
    @cache
    def centres_inside() -> BoolArray:
        return centre_in_intersection(ego)

    keeping = _lane_keeping(ego, settings, centres_inside)
    comfort = {
        at_centre: ego.per_token(comfort_series(ego.rows, at_centre=at_centre))
        for at_centre in dict.fromkeys(setting.comfort_at_centre for setting in settings)
    }
    off_route = {
        excludes: ego.per_token(
            off_route_steps(ego.points, ego.areas, centres_inside() if excludes else None)
        )
        for excludes in dict.fromkeys(setting.ddc_excludes_intersections for setting in settings)
    }
    shared = {
        "drivable_area_compliance": ego.per_token(drivable_area_compliance(ego.areas)),
        "progress_raw": ego.per_token(raw_progress(ego.points, ego.centerlines, ego.row_token)),
        "ego_areas": ego.per_token(ego.areas),
    }
    return [
        _setting_measures(
            ego,
            observed[key],
            ttc[key, setting.stopped_speed_threshold, setting.ttc_evaluated_steps],
            lights[key] if setting.traffic_light_compliance else None,
            None if setting.lane_keeping is None else keeping[setting.lane_keeping],
            {
                **shared,
                "comfort_series": comfort[setting.comfort_at_centre],
                "off_route_steps": off_route[setting.ddc_excludes_intersections],
            },
        )
        for setting, key in readers
    ]


def _setting_measures(
    ego: EgoRows,
    seen: _Observed,
    ttc: tuple[FloatArray, FirstInfraction],
    light: TrafficLights | None,
    lane: LaneKeeping | None,
    per_token: Mapping[str, np.ndarray],
) -> ProposalMeasures:
    """Return one setting's measures (B, P) from the per-row ones it reads and those already `per_token`
    (B, P, ...); without TLC or LK (None) it gets 1 and no infraction."""
    num_rows = len(ego.rows)
    no_index = np.full(num_rows, -1, dtype=np.intp)
    if light is None:
        light = (np.ones(num_rows), no_index, no_index)
    if lane is None:
        lane = (np.ones(num_rows), no_index, np.zeros(num_rows, dtype=np.intp))
    ttc_within_bound, ttc_infraction = ttc
    return ProposalMeasures(
        **per_token,
        no_at_fault_collisions=ego.per_token(seen.collisions),
        collision_index=ego.per_token(seen.collision.time_index),
        collision_object=ego.per_token(seen.local_object(seen.collision.obj)),
        time_to_collision_within_bound=ego.per_token(ttc_within_bound),
        ttc_index=ego.per_token(ttc_infraction.time_index),
        ttc_object=ego.per_token(seen.local_object(ttc_infraction.obj)),
        traffic_light_compliance=ego.per_token(light[0]),
        red_light_index=ego.per_token(light[1]),
        red_light=ego.per_token(light[2]),
        lane_keeping=ego.per_token(lane[0]),
        lane_keeping_index=ego.per_token(lane[1]),
        lane_keeping_run=ego.per_token(lane[2]),
    )


def comfort_of(series: FloatArray, known: list[tuple[FloatArray, BoolArray]]) -> BoolArray:
    """Return v1's comfort (B, P) of B tokens' proposals' comfort series (B, P, n, c) (`is_comfortable`), and
    add both to `known`: the series and comfort of the batches measured before it.

    A token's proposals are filtered as one group and judged on their own, so a token whose series an
    earlier batch of the same shape held to the bit gets that batch's answer: v1.0 and v1.1 score the same
    agents against PDM-Closed references that are mostly the same trajectories.
    """
    comfortable = np.empty(series.shape[:2], dtype=bool)
    unknown = np.ones(len(series), dtype=bool)
    bits = series.view(np.uint64)
    for known_series, known_comfort in known:
        if known_series.shape == series.shape:
            same = unknown & (known_series.view(np.uint64) == bits).all(axis=(1, 2, 3))
            comfortable[same] = known_comfort[same]
            unknown &= ~same
    if unknown.any():
        comfortable[unknown] = is_comfortable(series[unknown], SCORING_INTERVAL_S)
    known.append((series, comfortable))
    return comfortable


def score_measures(
    measures: ProposalMeasures,
    config: ScorerConfig,
    pasts: Sequence[FloatArray | None] | None = None,
    comfortable: BoolArray | None = None,
) -> ProposalScores:
    """Return the scores (B, P) from the proposals' measures: DDC windows, EP normalisation, comfort,
    aggregation: the steps in which the devkit's result for a proposal depends on the others.

    `pasts` are each token's past ego states (`history_comfort.past_states`) for v2's history comfort;
    without them (PDM-Closed's own ranking, the human of the filter) the devkit leaves HC at 1.
    `comfortable` is v1's comfort (B, P) where the caller has it already: `comfort_of` these measures.
    """
    ones = np.ones_like(measures.progress_raw)
    weights = config.weights
    comfort = ones
    if "comfortable" in weights:
        if comfortable is None:
            comfortable = is_comfortable(measures.comfort_series, SCORING_INTERVAL_S)
        comfort = comfortable.astype(np.float64)
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
