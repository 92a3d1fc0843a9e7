"""What decided one token's score: the simulated trajectories, the metrics, and where each infraction happened.

The drill-down pictures draw it (`scorer.picture`, for `navsim-lb plot` and the server). It makes the
scoring's own calls (`evaluate.score_against_references` on the token's metric cache), so its numbers are
the leaderboard's. The infractions are the first of each kind on the submitted trajectory, as the metrics see
them: an at-fault collision (NC) and a time-to-collision violation (TTC) with the object involved, the first
state off the drivable area (DAC), and the first state in oncoming traffic when DDC is below 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scorer.cache import MetricCache, load_cache
from scorer.evaluate import (
    ROW_COLUMNS,
    TokenError,
    build_missing_caches,
    score_against_references,
    token_result,
)
from scorer.geometry import FloatArray
from scorer.metrics.ego_areas import EgoArea
from scorer.scene import load_scene, scene_file_hash
from scorer.simulation import simulate
from scorer.trajectory import SCORING_INTERVAL_S, initial_state, pdm_references
from scorer.versions import VersionName, cached_together, get_version

AGENT = 1  # proposal 0 is the PDM-Closed reference


@dataclass(frozen=True)
class Infraction:
    """The first infraction of one kind: when, and the object involved (None for the map's)."""

    kind: str  # "collision", "time to collision", "off the drivable area", "oncoming traffic"
    time_s: float
    object_index: int | None  # in the observation of the token's metric cache
    object_token: str | None
    object_type: str | None


@dataclass(frozen=True, eq=False)
class Explanation:
    token: str
    version: VersionName
    metrics: dict[str, float]  # the submission's result columns, the token scored alone (v2.2's EC: NaN)
    reference_metrics: dict[str, float]  # PDM-Closed's, scored beside it
    reference_states: FloatArray  # (41, 11) PDM-Closed's trajectory as the simulator tracks it
    agent_states: FloatArray  # (41, 11) the submitted trajectory as the simulator tracks it
    human_future: FloatArray  # (k, 3) the recorded ego's rear-axle poses after the current frame, 2 Hz
    infractions: tuple[Infraction, ...]
    cache: MetricCache  # observation, drivable map, centerline and route of the token


def _cache(scene: Path, cache_dir: Path, token: str, version: VersionName) -> MetricCache:
    cache = load_cache(Path(cache_dir), version, token, scene_file_hash(scene))
    if cache is not None:
        return cache
    built, errors = build_missing_caches([scene], Path(cache_dir), cached_together([version]))
    if version not in built.get(scene.name, {}):
        raise TokenError(f"the metric cache of {token} could not be built: {errors[scene.name]}")
    return built[scene.name][version]


def _object(cache: MetricCache, index: int) -> tuple[int | None, str | None, str | None]:
    if index < 0:
        return None, None, None
    return index, cache.observation.tokens[index], cache.observation.object_types[index]


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
    token_scores = scores.token(0)
    areas = token_scores.ego_areas[AGENT]
    found = [
        ("collision", int(token_scores.collision_index[AGENT]), int(token_scores.collision_object[AGENT])),
        ("time to collision", int(token_scores.ttc_index[AGENT]), int(token_scores.ttc_object[AGENT])),
        ("off the drivable area", _first_step(areas[:, EgoArea.NON_DRIVABLE_AREA]), -1),
    ]
    if token_scores.driving_direction_compliance[AGENT] < 1.0:
        found.append(("oncoming traffic", _first_step(areas[:, EgoArea.ONCOMING_TRAFFIC]), -1))
    infractions = tuple(
        Infraction(kind, round(step * SCORING_INTERVAL_S, 1), *_object(cache, obj))
        for kind, step, obj in found
        if step >= 0
    )
    return Explanation(
        token=token,
        version=metric_version.name,
        metrics=token_result(cache, None, scores, 0, metric_version).metrics,
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
    )
