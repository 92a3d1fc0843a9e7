"""What decided one token's score: the simulated trajectories, the metrics, and where each infraction happened.

The drill-down pictures draw it (`scorer.picture`, for `navsim-lb plot` and the server). It makes the
scoring's own calls (`evaluate.score_against_references` on the token's metric cache), so its numbers are
the leaderboard's. The infractions are the first of each kind on the submitted trajectory, as the metrics see
them: an at-fault collision (NC) and a time-to-collision violation (TTC) with the object involved, the first
state off the drivable area (DAC), the first state in oncoming traffic when DDC is below 1, and under v2 the
first contact with a red light (TLC) and where lane keeping (LK) failed.

The objects are those the version scored against: under reactive traffic, the vehicles as they reacted to
the submitted trajectory (the cache holds only their starting traffic). On a two-stage split, a stage-one
token carries the synthetic starts of its stage two, weighted against its submitted endpoint.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import shapely

from scorer.cache import MetricCache, load_cache
from scorer.evaluate import (
    ROW_COLUMNS,
    TokenError,
    build_missing_caches,
    score_against_references,
    token_results,
)
from scorer.geometry import FloatArray
from scorer.metrics.ego_areas import EgoArea
from scorer.observation import Observation
from scorer.reactive.observation import reacting_observation
from scorer.scene import SceneFormatError, load_scene, scene_file_hash, scene_paths
from scorer.simulation import simulate
from scorer.trajectory import SCORING_INTERVAL_S, initial_state, pdm_references
from scorer.two_stage.split import TwoStageSplitError
from scorer.two_stage.starts import StageTwoPlace, SyntheticStarts, stage_two_place, synthetic_starts
from scorer.versions import VersionName, cached_together, get_version

AGENT = 1  # proposal 0 is the PDM-Closed reference


# The result column each kind of infraction takes down.
INFRACTION_COLUMNS = {
    "collision": "no_at_fault_collisions",
    "time to collision": "time_to_collision_within_bound",
    "off the drivable area": "drivable_area_compliance",
    "oncoming traffic": "driving_direction_compliance",
    "red light": "traffic_light_compliance",
    "lane keeping": "lane_keeping",
}


@dataclass(frozen=True)
class Infraction:
    """The first infraction of one kind: when, and the object involved (None for the map's)."""

    kind: str  # "collision", "time to collision", "off the drivable area", "oncoming traffic", ...
    time_s: float
    object_index: int | None  # in the explanation's observation
    object_token: str | None
    object_type: str | None
    red_light: int | None = None  # the light touched, its index in the observation's red lights


@dataclass(frozen=True, eq=False)
class Explanation:
    token: str
    version: VersionName
    metrics: dict[str, float]  # the submission's result columns, the token scored alone (v2.2's EC: NaN)
    filtered: tuple[str, ...]  # the columns the human filter set to 1 (v2): the logged human fails them too
    reference_metrics: dict[str, float]  # PDM-Closed's, scored beside it
    reference_states: FloatArray  # (41, 11) PDM-Closed's trajectory as the simulator tracks it
    agent_states: FloatArray  # (41, 11) the submitted trajectory as the simulator tracks it
    human_future: FloatArray  # (k, 3) the recorded ego's rear-axle poses after the current frame, 2 Hz
    infractions: tuple[Infraction, ...]
    cache: MetricCache  # drivable map, centerline and route of the token
    observation: Observation  # the objects as scored: under reactive traffic, reacting to the submission
    non_drivable: tuple[
        tuple[str, shapely.Polygon], ...
    ]  # the map's crosswalks and walkways: (layer, polygon)
    synthetic_starts: SyntheticStarts | None = None  # a stage-one token's stage two (two-stage versions)
    stage_two_place: StageTwoPlace | None = None  # a synthetic token's place in the stage mapping (likewise)


def _cache(scene: Path, cache_dir: Path, token: str, version: VersionName) -> MetricCache:
    cache = load_cache(Path(cache_dir), version, token, scene_file_hash(scene))
    if cache is not None:
        return cache
    built, errors = build_missing_caches([scene], Path(cache_dir), cached_together([version]))
    if version not in built.get(scene.name, {}):
        raise TokenError(f"the metric cache of {token} could not be built: {errors[scene.name]}")
    return built[scene.name][version]


def _object(observation: Observation, index: int) -> tuple[int | None, str | None, str | None]:
    if index < 0:
        return None, None, None
    return index, observation.tokens[index], observation.object_types[index]


def _first_step(flags: np.ndarray) -> int:
    steps = np.flatnonzero(flags)
    return int(steps[0]) if len(steps) else -1


def explain_token(
    scene_file: Path, cache_dir: Path, token: str, poses: FloatArray, version: str
) -> Explanation:
    """Return the explanation of `poses` (8, 3) on `token`, whose scene is `scene_file`, under a metric version."""
    metric_version = get_version(version)
    cache = _cache(scene_file, Path(cache_dir), token, metric_version.name)
    scene = load_scene(scene_file)
    future = scene.frames[scene.current_index + 1 :]
    agent_states, scores = score_against_references(
        [cache], [np.asarray(poses, dtype=np.float64)], metric_version
    )
    start = initial_state(cache.ego)[None]
    reference_states = simulate(
        pdm_references(np.array([cache.t0_us], dtype=np.int64), cache.trajectory[None]), start
    )[0]
    observation = cache.observation
    if metric_version.reactive_traffic is not None and cache.starting_traffic is not None:
        # What `_score_reacting` scored against; the object indices of the scores are its columns.
        observation = reacting_observation(
            cache.starting_traffic, cache.observation, agent_states[0], metric_version.reactive_traffic
        )
    token_scores = scores.token(0)
    areas = token_scores.ego_areas[AGENT]
    found = [
        ("collision", int(token_scores.collision_index[AGENT]), int(token_scores.collision_object[AGENT])),
        ("time to collision", int(token_scores.ttc_index[AGENT]), int(token_scores.ttc_object[AGENT])),
        ("off the drivable area", _first_step(areas[:, EgoArea.NON_DRIVABLE_AREA]), -1),
    ]
    if token_scores.driving_direction_compliance[AGENT] < 1.0:
        found.append(("oncoming traffic", _first_step(areas[:, EgoArea.ONCOMING_TRAFFIC]), -1))
    if token_scores.lane_keeping[AGENT] < 1.0:
        found.append(("lane keeping", int(token_scores.lane_keeping_index[AGENT]), -1))
    infractions = [
        Infraction(kind, round(step * SCORING_INTERVAL_S, 1), *_object(observation, obj))
        for kind, step, obj in found
        if step >= 0
    ]
    light_step, light = int(token_scores.red_light_index[AGENT]), int(token_scores.red_light[AGENT])
    if light_step >= 0 and observation.red_lights is not None:
        lane = observation.red_lights.lane_ids[light]
        infractions.append(
            Infraction("red light", round(light_step * SCORING_INTERVAL_S, 1), None, lane, "lane", light)
        )
    (row,) = token_results([cache], None, scores, metric_version)
    return Explanation(
        token=token,
        version=metric_version.name,
        metrics=row.metrics,
        filtered=tuple(row.detail.get("human_filter", {}).get("overridden", ())),
        reference_metrics={
            column: float(getattr(token_scores, column)[0])
            for column in metric_version.result_columns
            if column in ROW_COLUMNS
        },
        reference_states=reference_states,
        agent_states=agent_states[0],
        human_future=np.array([(frame.ego.x, frame.ego.y, frame.ego.heading) for frame in future]).reshape(
            -1, 3
        ),
        infractions=tuple(sorted(infractions, key=lambda infraction: infraction.time_s)),
        cache=cache,
        observation=observation,
        non_drivable=tuple(
            (layer, area.polygon)
            for layer, areas in (("crosswalk", scene.map.crosswalks), ("walkway", scene.map.walkways))
            for area in areas
        ),
    )


def explain_split_token(
    split_dir: Path, cache_dir: Path, token: str, poses: FloatArray, version: str
) -> Explanation:
    """Return the explanation (`explain_token`) of `poses` on `token` of the split at `split_dir`; under a
    two-stage version, a stage-one token's carries the synthetic starts of its stage two, a synthetic token's
    its place in the stage mapping. Raises TokenError
    for a token the split lacks or a stage mapping that cannot be read."""
    scenes = scene_paths(split_dir)
    if token not in scenes:
        raise TokenError(f"token {token} is not part of split {Path(split_dir).name}")
    explanation = explain_token(scenes[token], cache_dir, token, poses, version)
    if not get_version(version).two_stage:
        return explanation
    try:
        starts = synthetic_starts(split_dir, token, poses, explanation.agent_states[0, :3])
        place = stage_two_place(split_dir, token)
    except (TwoStageSplitError, SceneFormatError) as error:
        raise TokenError(f"the stage mapping of split {Path(split_dir).name}: {error}") from None
    return replace(explanation, synthetic_starts=starts, stage_two_place=place)
