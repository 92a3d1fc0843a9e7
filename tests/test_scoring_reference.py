"""The scorer against the official devkit's per-token results: 13 families x 40 tokens x v1.0 and v1.1.

Inputs come from the scene (our observation and drivable-area map, checked against the official cache
first) and from each expected line's `cache` block (PDM-Closed trajectory, centerline, route lane ids),
so PDM-Closed and the scorer are tested apart. Both proposals are sampled and simulated with
`scorer.trajectory` / `scorer.simulation`.

Two runs:
- the scorer alone: x, y and heading of the simulated states are the devkit's own simulated poses
  (diagnostics `pdm_simulated` / `pred_simulated`); every column, diagnostic and ego-area flag must be
  equal as floats;
- end to end with our simulation: equal as floats under the official results' OpenBLAS kernels; under
  others the simulator differs in the last bits on curving trajectories (see `test_simulation_reference`),
  which moves raw progress, hence EP and the score, by about 1e-11; every discrete result must still be
  equal.
"""

from __future__ import annotations

import gzip
import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from devkit_kernels import CONTINUOUS_TOLERANCE, V1_VERSIONS
from engine_scoring import score_proposals

from scorer.drivable_map import DrivableMap, build_drivable_map
from scorer.metrics.ego_areas import EgoArea
from scorer.observation import Observation, observe_scene
from scorer.pdm_scorer import ProposalScores
from scorer.scene import Scene, load_scene
from scorer.simulation import simulate
from scorer.trajectory import SCORING_INTERVAL_S, agent_references, initial_state, pdm_references
from scorer.versions import METRIC_COLUMNS, get_version

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
FAMILIES = sorted(path.stem for path in (REFERENCE / "submissions").glob("*.json"))
VERSIONS = V1_VERSIONS
DISCRETE_COLUMNS = tuple(column for column in METRIC_COLUMNS if column not in ("ego_progress", "score"))


@dataclass(frozen=True)
class Case:
    family: str
    version: str
    row: dict
    states: np.ndarray  # (2, 41, 11) our simulation: PDM-Closed reference, submission


@cache
def _scene(token: str) -> Scene:
    return load_scene(REFERENCE / "scenes" / f"{token}.json.gz")


@cache
def _inputs(token: str) -> tuple[Observation, DrivableMap]:
    scene = _scene(token)
    return observe_scene(scene), build_drivable_map(scene)


@cache
def _cases() -> tuple[Case, ...]:
    labelled = []
    for family in FAMILIES:
        predictions = json.loads((REFERENCE / "submissions" / f"{family}.json").read_text())["predictions"]
        for version in VERSIONS:
            with gzip.open(REFERENCE / "expected" / f"{family}.{version}.jsonl.gz", "rt") as handle:
                labelled += [
                    (family, version, row, predictions[row["token"]]) for row in map(json.loads, handle)
                ]
    frames = [_scene(row["token"]).current_frame for _, _, row, _ in labelled]
    initial = np.array([initial_state(frame.ego) for frame in frames])
    t0_us = np.array([frame.timestamp_us for frame in frames])
    agents = agent_references(initial, t0_us, np.array([poses for *_, poses in labelled], dtype=np.float64))
    pdm = pdm_references(
        t0_us,
        np.array([np.asarray(row["cache"]["pdm_closed_trajectory"])[:, 1:4] for _, _, row, _ in labelled]),
    )
    simulated = simulate(np.concatenate([pdm, agents]), np.concatenate([initial, initial]))
    states = np.stack(np.split(simulated, 2), axis=1)
    return tuple(
        Case(family, version, row, pair)
        for (family, version, row, _), pair in zip(labelled, states, strict=True)
    )


def _score(case: Case, states: np.ndarray) -> ProposalScores:
    observation, drivable_map = _inputs(case.row["token"])
    cached = case.row["cache"]
    return score_proposals(
        states,
        observation,
        drivable_map,
        np.asarray(cached["centerline"])[:, :2],
        cached["route_lane_ids"],
        get_version(case.version).evaluation,
    )


def _time(index: int) -> float | None:
    return None if index < 0 else index * SCORING_INTERVAL_S


def _flags(areas: np.ndarray) -> dict[str, str]:
    return {area.name: "".join("1" if flag else "0" for flag in areas[:, area]) for area in EgoArea}


def _differences(case: Case, scores: ProposalScores, continuous: bool) -> list[str]:
    row, diagnostics = case.row, case.row["diagnostics"]
    found = {
        column: (float(getattr(scores, column)[1]), row[column])
        for column in (METRIC_COLUMNS if continuous else DISCRETE_COLUMNS)
    }
    found["collision_time_s"] = (_time(scores.collision_index[1]), diagnostics["collision_time_s"])
    found["ttc_time_s"] = (_time(scores.ttc_index[1]), diagnostics["ttc_time_s"])
    found["pred_ego_areas"] = (_flags(scores.ego_areas[1]), diagnostics["pred_ego_areas"])
    if continuous:
        found["progress_raw_m"] = (scores.progress_raw.tolist(), diagnostics["progress_raw_m"])
        found["pdm_closed_subscores"] = (scores.subscores(0), diagnostics["pdm_closed_subscores"])
    else:
        subscores = scores.subscores(0)
        found["pdm_closed_subscores"] = (
            {name: value for name, value in subscores.items() if name not in ("progress", "score")},
            {
                name: value
                for name, value in diagnostics["pdm_closed_subscores"].items()
                if name not in ("progress", "score")
            },
        )
    label = f"{case.family} {case.version} {row['token']}"
    return [
        f"{label} {name}: {ours!r} != {theirs!r}" for name, (ours, theirs) in found.items() if ours != theirs
    ]


def test_every_family_token_and_version_is_covered() -> None:
    assert len(FAMILIES) == 13
    assert len(_cases()) == 13 * 40 * 2


@pytest.mark.parametrize("version", VERSIONS)
def test_observation_and_drivable_map_match_the_official_cache(version: str) -> None:
    for case in _cases():
        if case.family != "human" or case.version != version:
            continue
        observation, drivable_map = _inputs(case.row["token"])
        by_type: dict[str, list[str]] = {}
        for token, kind in zip(drivable_map.tokens, drivable_map.types, strict=True):
            by_type.setdefault(kind, []).append(token)
        assert by_type == case.row["cache"]["drivable_map"], case.row["token"]
        assert len(observation.tokens) == case.row["cache"]["observation_tracks"], case.row["token"]


@pytest.mark.parametrize("version", VERSIONS)
def test_the_scorer_on_the_devkits_simulated_poses_is_bit_exact(version: str) -> None:
    failures = []
    for case in _cases():
        if case.version != version:
            continue
        states = case.states.copy()
        states[0, :, :3] = case.row["diagnostics"]["pdm_simulated"]
        states[1, :, :3] = case.row["diagnostics"]["pred_simulated"]
        failures += _differences(case, _score(case, states), continuous=True)
    assert failures == []


@pytest.mark.parametrize("version", VERSIONS)
def test_end_to_end_with_our_simulation_every_discrete_result_is_exact(version: str) -> None:
    failures = []
    for case in _cases():
        if case.version != version:
            continue
        scores = _score(case, case.states)
        failures += _differences(case, scores, continuous=False)
        ours = [float(scores.ego_progress[1]), float(scores.score[1]), *scores.progress_raw.tolist()]
        theirs = [case.row["ego_progress"], case.row["score"], *case.row["diagnostics"]["progress_raw_m"]]
        if not np.allclose(ours, theirs, rtol=CONTINUOUS_TOLERANCE, atol=0.0):
            failures.append(f"{case.family} {version} {case.row['token']}: {ours} vs {theirs}")
    assert failures == []
