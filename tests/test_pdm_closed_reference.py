"""PDM-Closed against the official devkit's metric cache on the 40 reference scenes, every version, exactly.

The `cache` block of every v1.x expected line holds the corrected route, the route lane ids, the
centerline, the IDM target speeds and the cached PDM-Closed trajectory (51 x [t_s, x, y, heading, v];
poses are what the cached EgoStates report, i.e. after the rear-axle round trip; row 0 is the path pose
at the ego's initial progress). The v2.2 results hold the trajectory and the selected proposal in their
diagnostics (v2.2 ranks the same proposals with its own scorer).
"""

from __future__ import annotations

import gzip
import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from scorer import pdm_closed
from scorer.drivable_map import build_drivable_map
from scorer.geometry import rear_axle_round_trip
from scorer.pdm_closed import (
    PROPOSAL_STEPS,
    PlannerOutput,
    plan_references_batch,
    plan_scene,
    unroll_proposals,
)
from scorer.scene import Scene, load_scene
from scorer.versions import LOG_REPLAY_VERSIONS, VERSIONS

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
EPDMS = Path(__file__).parent / "fixtures" / "epdms" / "expected"
SCENES = sorted(path.name.removesuffix(".json.gz") for path in (REFERENCE / "scenes").glob("*.json.gz"))
V1_VERSIONS = ("v1.0", "v1.1")  # the versions whose expected lines hold the whole cache


@cache
def _expected_cache(version: str) -> dict[str, dict[str, object]]:
    if version in V1_VERSIONS:
        with gzip.open(REFERENCE / "expected" / f"human.{version}.jsonl.gz", "rt") as handle:
            return {row["token"]: row["cache"] for row in map(json.loads, handle)}
    with gzip.open(EPDMS / f"human.{version}.jsonl.gz", "rt") as handle:
        return {row["token"]: row["diagnostics"] for row in map(json.loads, handle)}


@cache
def _scene(token: str) -> Scene:
    return load_scene(REFERENCE / "scenes" / f"{token}.json.gz")


@cache
def _plans(token: str) -> dict[str, PlannerOutput]:
    scene = _scene(token)
    (outputs,) = plan_references_batch(
        [scene], [build_drivable_map(scene)], [version.planner for version in VERSIONS.values()]
    )
    return dict(zip(VERSIONS, outputs, strict=True))


@pytest.mark.parametrize("version", V1_VERSIONS)
@pytest.mark.parametrize("token", SCENES)
def test_route_centerline_and_targets_match_the_devkit(token: str, version: str) -> None:
    expected = _expected_cache(version)[token]
    plan = _plans(token)[version]
    assert list(plan.route_roadblocks) == expected["route_roadblocks_corrected"]
    assert list(plan.route_lane_ids) == expected["route_lane_ids"]
    assert plan.centerline.tolist() == expected["centerline"]
    assert plan.idm_target_velocities.tolist() == expected["idm_target_velocities"]


@pytest.mark.parametrize("version", LOG_REPLAY_VERSIONS)  # the one-stage references' versions
@pytest.mark.parametrize("token", SCENES)
def test_reference_trajectory_matches_the_devkit(token: str, version: str) -> None:
    expected = np.array(_expected_cache(version)[token]["pdm_closed_trajectory"])
    plan = _plans(token)[version]
    # The stored knots are at t0 + k * 100000 us; the cache holds poses only.
    assert expected[:, 0].tolist() == [k * 100_000 * 1e-6 for k in range(51)]
    assert not expected[:, 4].any()
    assert plan.trajectory.shape == (51, 3)
    mismatched_rows = np.flatnonzero((plan.trajectory != expected[:, 1:4]).any(axis=1))
    assert mismatched_rows.tolist() == []
    if version not in V1_VERSIONS:
        assert plan.proposal == _expected_cache(version)[token]["pdm_closed_proposal_idx"]


@cache
def _unrolled_together() -> tuple[np.ndarray, dict[str, int]]:
    """The 15 proposals of every reference scene, unrolled in one batch, as stored (51 poses)."""
    scenes = [_scene(token) for token in SCENES]
    proposals = unroll_proposals([plan_scene(scene, build_drivable_map(scene)) for scene in scenes])
    rows = np.arange(15 * len(scenes))
    proposals.unroll.run(rows, range(PROPOSAL_STEPS + 1, 51), groups=rows)  # every proposal extended alone
    poses = proposals.poses(rows, slice(0, 51))
    x, y = rear_axle_round_trip(poses[..., 0], poses[..., 1], poses[..., 2])
    return np.stack([x, y, poses[..., 2]], axis=-1).reshape(len(scenes), 15, 51, 3), {
        t: i for i, t in enumerate(SCENES)
    }


@pytest.mark.parametrize("token", SCENES)
def test_some_unrolled_proposal_is_the_devkit_trajectory(token: str) -> None:
    """Independent of the proposal scoring: the devkit's trajectory, all 51 poses, is one of our 15 proposals."""
    stored, index = _unrolled_together()
    for version in (*V1_VERSIONS, "v2.2"):
        expected = np.array(_expected_cache(version)[token]["pdm_closed_trajectory"])[:, 1:4]
        assert any(np.array_equal(stored[index[token], row], expected) for row in range(15)), version


def test_a_batch_of_scenes_unrolls_as_each_scene_alone() -> None:
    stored, index = _unrolled_together()
    for token in SCENES[:3]:
        scene = _scene(token)
        alone = unroll_proposals([plan_scene(scene, build_drivable_map(scene))])
        rows = np.arange(15)
        alone.unroll.run(rows, range(PROPOSAL_STEPS + 1, 51), groups=rows)
        poses = alone.poses(rows, slice(0, 51))
        x, y = rear_axle_round_trip(poses[..., 0], poses[..., 1], poses[..., 2])
        assert np.array_equal(np.stack([x, y, poses[..., 2]], axis=-1), stored[index[token]])


def test_planning_a_scene_twice_or_after_another_scene_gives_the_same_result() -> None:
    """Per-scene isolation: nothing (such as the devkit's collided-token list) carries over."""
    first, other = _scene(SCENES[0]), _scene(SCENES[1])
    config = VERSIONS["v1.1"].planner
    ((before,),) = plan_references_batch([first], [build_drivable_map(first)], [config])
    plan_references_batch([other], [build_drivable_map(other)], [config])
    ((after,),) = plan_references_batch([first], [build_drivable_map(first)], [config])
    assert np.array_equal(before.trajectory, after.trajectory) and before.proposal == after.proposal


def test_given_the_devkits_choice_every_cached_field_matches(monkeypatch: pytest.MonkeyPatch) -> None:
    """The whole batch pipeline with the proposal scoring replaced by the devkit's known choice.

    Isolates the planner from the scorer: each expected trajectory's first 4 s is exactly one proposal.
    """
    stored, index = _unrolled_together()
    versions = list(V1_VERSIONS)
    choices: list[np.ndarray] = []
    for token in SCENES:
        for version in versions:
            expected = np.array(_expected_cache(version)[token]["pdm_closed_trajectory"])[
                : PROPOSAL_STEPS + 1, 1:4
            ]
            choice = np.array(
                [
                    np.array_equal(stored[index[token], row, : PROPOSAL_STEPS + 1], expected)
                    for row in range(15)
                ]
            )
            assert choice.sum() == 1, (token, version)
            choices.append(choice.astype(np.float64))
    best = np.argmax(choices, axis=1).reshape(len(SCENES), len(versions))
    monkeypatch.setattr(pdm_closed, "best_proposals", lambda *args: best)
    scenes = [_scene(token) for token in SCENES]
    outputs = plan_references_batch(
        scenes, [build_drivable_map(s) for s in scenes], [VERSIONS[v].planner for v in versions]
    )
    for token, scene_outputs in zip(SCENES, outputs, strict=True):
        for version, plan in zip(versions, scene_outputs, strict=True):
            expected = _expected_cache(version)[token]
            assert list(plan.route_roadblocks) == expected["route_roadblocks_corrected"]
            assert list(plan.route_lane_ids) == expected["route_lane_ids"]
            assert plan.centerline.tolist() == expected["centerline"]
            assert plan.idm_target_velocities.tolist() == expected["idm_target_velocities"]
            assert np.array_equal(plan.trajectory, np.array(expected["pdm_closed_trajectory"])[:, 1:4]), (
                token,
                version,
            )
