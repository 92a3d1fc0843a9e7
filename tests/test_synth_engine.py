"""Synthetic scenes go through the whole engine: metric cache (PDM-Closed) and scoring in v1.0, v1.1, v2.2."""

from __future__ import annotations

import json

import numpy as np
import pytest
from engine_scoring import score_caches

from scorer.cache import build_caches
from scorer.scene import Scene, iter_scenes
from scorer.synth import synthesize_split
from scorer.versions import VERSIONS

POSE_TIMES = np.arange(1, 9) * 0.5


def _recorded_future(scene: Scene) -> np.ndarray:
    """Return the recorded ego's next 8 poses in the ego frame of the current frame."""
    ego = scene.current_frame.ego
    c, s = np.cos(ego.heading), np.sin(ego.heading)
    future = scene.frames[scene.current_index + 1 : scene.current_index + 9]
    dx = np.array([f.ego.x - ego.x for f in future])
    dy = np.array([f.ego.y - ego.y for f in future])
    heading = np.array([f.ego.heading - ego.heading for f in future])
    return np.stack(
        [c * dx + s * dy, -s * dx + c * dy, np.arctan2(np.sin(heading), np.cos(heading))], axis=-1
    )


def _constant_velocity(scene: Scene) -> np.ndarray:
    speed = scene.current_frame.ego.vx
    return np.stack([speed * POSE_TIMES, np.zeros(8), np.zeros(8)], axis=-1)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Scene], dict[str, str]]:
    split = tmp_path_factory.mktemp("synth_engine") / "split"
    synthesize_split(split, 10, 3)
    kinds = {note["token"]: note["kind"] for note in json.loads((split / "split.json").read_text())["scenes"]}
    return list(iter_scenes(split)), kinds


def test_synthetic_scenes_are_cached_and_scored_in_every_version(
    scenes: tuple[list[Scene], dict[str, str]],
) -> None:
    loaded, kinds = scenes
    assert {"intersection", "carpark_start"} <= set(kinds.values()) and {
        "straight",
        "curve",
        "carpark",
    } & set(kinds.values())
    for scene in loaded:
        caches = build_caches(scene, list(VERSIONS.values()))
        for name, cache in caches.items():
            assert len(cache.centerline) > 10 and cache.route_lane_ids, (scene.token, name)
            # One call each: a batch names the states by token.
            (human,) = score_caches([cache], [_recorded_future(scene)], VERSIONS[name])
            (constant,) = score_caches([cache], [_constant_velocity(scene)], VERSIONS[name])
            for result in (human, constant):
                assert result.valid, (scene.token, name, result.error)
                columns = [c for c in VERSIONS[name].result_columns if c != "two_frame_extended_comfort"]
                assert all(0.0 <= result.metrics[column] <= 1.0 for column in columns)
            # The recorded human drives without collision and stays on the drivable area.
            assert human.metrics["no_at_fault_collisions"] == 1.0, (scene.token, name)
            assert human.metrics["drivable_area_compliance"] == 1.0, (scene.token, name)
