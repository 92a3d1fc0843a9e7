"""Reactive traffic (v2.2-two-stage) against the official NAVSIM v2.2 two-stage run, bit for bit
(fixtures/epdms-two-stage-reactive/README.md).

The first 3 groups of the reference split (36 tokens: 6 logged, 30 synthetic): the IDM vehicles as built at
the start (segment, progress, speed, target velocity, path, snapped box, rejections) equal the official ones;
stepped against the agents' and the logged humans' simulated trajectories, every IDM update (lead, distance,
speed, state before and after) and every vehicle's box at each of the 41 steps equal the official trace; and
the per-token subscores of every family, after the human filter, equal the official ones. Exact equality
throughout under the official results' OpenBLAS kernels (SkylakeX, an AVX-512 host); under others the ego's
simulated states move in their last bits (the tracker's `pinv`, as the devkit's own would), so there the
floats of the IDM trace and the scores are compared within 1e-9 and everything discrete still exactly.
"""

from __future__ import annotations

import gzip
import json
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from devkit_kernels import same_values

from scorer.evaluate import build_split_cache, score_tokens
from scorer.human import FILTERED_COLUMNS, human_future_poses
from scorer.pdm_closed import ego_polygons
from scorer.reactive.agents import StartingTraffic, build_agents
from scorer.reactive.traffic import VehicleSteps, simulate_traffic
from scorer.scene import Scene, load_scene, scene_paths
from scorer.simulation import simulate
from scorer.trajectory import agent_references, initial_state
from scorer.versions import VERSIONS, VersionName

FIXTURES = Path(__file__).parent / "fixtures" / "epdms-two-stage-reactive"
VERSION = VERSIONS[VersionName.V2_2_TWO_STAGE]
CONFIG = VERSION.reactive_traffic
TRACED = sorted(path.name.split(".")[0] for path in (FIXTURES / "trace").glob("*.idm_trace.jsonl.gz"))
AGENT_FIELDS = (
    "segment",
    "segment_layer",
    "progress0",
    "v0",
    "target_velocity",
    "lateral_deviation",
    "path",
    "box0",
)


@cache
def _expected() -> dict[tuple[str, str], dict[str, Any]]:
    with gzip.open(FIXTURES / "expected.jsonl.gz", "rt") as handle:
        return {(row["submission"], row["token"]): row for row in map(json.loads, handle)}


@cache
def _predictions() -> dict[str, dict[str, list[list[float]]]]:
    with gzip.open(FIXTURES / "predictions.json.gz", "rt") as handle:
        return json.load(handle)


@cache
def _scene(token: str) -> Scene:
    return load_scene(scene_paths(FIXTURES)[token])


@cache
def _traffic(token: str) -> StartingTraffic:
    scene = _scene(token)
    ego = scene.current_frame.ego
    assert CONFIG is not None
    initial_box = ego_polygons(np.array([[ego.x, ego.y, ego.heading]]))[0]
    return build_agents(scene.current_frame, scene.map, initial_box, CONFIG)


def _simulated(scene: Scene, poses: np.ndarray) -> np.ndarray:
    """The simulated states (41, 11) of poses (8, 3) in the scene's ego frame."""
    frame = scene.current_frame
    initial = initial_state(frame.ego)[None]
    return simulate(agent_references(initial, np.array([frame.timestamp_us]), poses[None]), initial)[0]


def _steps(token: str, family: str, key: str) -> VehicleSteps:
    scene = _scene(token)
    if key == "idm":
        poses = np.array(_predictions()[family][token], dtype=np.float64)
    else:
        poses = human_future_poses(scene)
    assert CONFIG is not None
    return simulate_traffic(_traffic(token), _simulated(scene, poses), CONFIG)


def _simulations() -> list[tuple[str, str]]:
    return [
        (token, key)
        for (family, token), row in _expected().items()
        if family == "human"
        for key in ("idm", "idm_human")
        if key in row
    ]


@pytest.mark.parametrize(("token", "key"), _simulations())
def test_agents_at_the_start_are_the_official_ones(token: str, key: str) -> None:
    """Every current vehicle is built (or rejected) as NAVSIM's builder does, for the agent and the human."""
    official = _expected()["human", token][key]
    traffic = _traffic(token)
    built = {
        agent.track: dict(
            zip(
                AGENT_FIELDS,
                (
                    agent.segment,
                    agent.segment_layer,
                    agent.progress,
                    agent.speed,
                    agent.target_velocity,
                    agent.lateral_deviation,
                    [agent.path.start, agent.path.end],
                    [*agent.pose, agent.length, agent.width],
                ),
                strict=True,
            )
        )
        for agent in traffic.agents
    }
    assert built == {
        track: {name: agent[name] for name in AGENT_FIELDS} for track, agent in official["agents"].items()
    }
    rejected = {
        track: {"reason": r.reason, "lateral_deviation": r.lateral_deviation, "segment": r.segment}
        for track, r in traffic.rejected.items()
    }
    assert rejected == official["rejected"]
    assert len(traffic.agents) + len(traffic.rejected) == official["n_vehicles"]


@pytest.mark.parametrize("family", TRACED)
def test_every_idm_update_and_box_is_the_official_one(family: str) -> None:
    """Stepped against the agent's and the human's simulated states, each IDM update and each vehicle box of
    the 41 steps equals the official trace, bit for bit."""
    with gzip.open(FIXTURES / "trace" / f"{family}.idm_trace.jsonl.gz", "rt") as handle:
        traces = [json.loads(line) for line in handle]
    assert len(traces) == 36
    for trace in traces:
        token = trace["token"]
        for key in ("idm", "idm_human"):
            if key not in trace:
                continue
            steps = _steps(token, family, key)
            updates = [
                [u.step, u.track, u.lead_track, u.lead.distance, u.lead.velocity, u.lead.length_rear, 0.1]
                + [*u.before, *u.after, u.target_velocity]
                for u in steps.updates
            ]
            assert same_values(updates, trace[key]["propagate"]), (token, key)
            frame = _scene(token).current_frame
            recorded = [
                [track, *box[[0, 1, 6, 3, 4]].tolist()]
                for track, category, box in zip(frame.tracks, frame.categories, frame.boxes, strict=True)
                if category == "vehicle"
            ]
            assert [box[:6] for box in trace[key]["vehicle_boxes"][0]] == recorded
            for step, vehicles in enumerate(steps.steps, 1):
                official = trace[key]["vehicle_boxes"][step]
                assert same_values([list(v) for v in vehicles], [box[:6] for box in official]), (
                    token,
                    key,
                    step,
                )
            official_final = {
                track: agent.get("final")
                for track, agent in _expected()[family, token][key]["agents"].items()
            }
            final = {agent.track: None for agent in _traffic(token).agents}
            final |= {update.track: list(update.after) for update in steps.updates}
            assert same_values(final, official_final)
            assert steps.out_of_range == _expected()[family, token][key]["out_of_range"]


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("cache")
    assert build_split_cache(FIXTURES, directory, [VERSION.name]) == {}
    return directory


@pytest.mark.parametrize("family", sorted(_predictions()))
def test_token_scores_are_the_official_ones(cache_dir: Path, family: str) -> None:
    """Each token's subscores after the human filter (stage one) or without it (stage two, synthetic) equal
    the official ones; the human filter overrides the same columns."""
    rows = score_tokens(FIXTURES, cache_dir, _predictions()[family], VERSION.name)
    assert len(rows) == 36
    for row in rows:
        official = _expected()[family, row.token]
        assert row.valid, row.error
        assert same_values(
            {column: row.metrics[column] for column in FILTERED_COLUMNS},
            {column: official[column] for column in FILTERED_COLUMNS},
        ), row.token
        if official["stage"] == "one":
            human = row.detail["human_filter"]["human"]
            assert same_values(
                {column: human[column] for column in FILTERED_COLUMNS},
                {column: official["human_filter"]["human"][column] for column in FILTERED_COLUMNS},
            ), row.token
            assert row.detail["human_filter"]["overridden"] == official["human_filter"]["overridden"], (
                row.token
            )
