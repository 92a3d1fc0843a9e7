"""Sampling and simulation against the official devkit's simulated poses (reference diagnostics).

Every token of every family and version: the submission (`pred_simulated`) and the re-simulated
PDM-Closed trajectory of that version's cache (`pdm_simulated`), 2080 trajectories in one batch.

Every pose must be equal under the official results' OpenBLAS kernels (`scorer.blas`). Under others,
`pinv` in the tracker's velocity and curvature fits rounds differently: curving trajectories move by at
most ~6e-11 m and ~4e-12 rad after 4 s (straight ones stay exact), hence the tolerances there.
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest
from devkit_kernels import V1_VERSIONS, devkit_tolerance

from scorer.geometry import normalize_angle
from scorer.scene import load_scene
from scorer.simulation import simulate
from scorer.trajectory import agent_references, initial_state, pdm_references

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
FAMILIES = sorted(path.stem for path in (REFERENCE / "submissions").glob("*.json"))
VERSIONS = V1_VERSIONS
POSITION_TOLERANCE_M = devkit_tolerance(1e-9)
HEADING_TOLERANCE_RAD = devkit_tolerance(1e-10)


class Cases:
    """All (family, version, token) cases: references, initial states and the devkit's simulated poses."""

    def __init__(self) -> None:
        scenes = {
            path.name.split(".")[0]: load_scene(path) for path in sorted((REFERENCE / "scenes").iterdir())
        }
        labels, initial, t0_us, agent_poses, pdm_poses, expected_agent, expected_pdm = (
            [],
            [],
            [],
            [],
            [],
            [],
            [],
        )
        for family in FAMILIES:
            predictions = json.loads((REFERENCE / "submissions" / f"{family}.json").read_text())[
                "predictions"
            ]
            for version in VERSIONS:
                with gzip.open(REFERENCE / "expected" / f"{family}.{version}.jsonl.gz", "rt") as handle:
                    for row in map(json.loads, handle):
                        frame = scenes[row["token"]].current_frame
                        labels.append((family, version, row["token"]))
                        initial.append(initial_state(frame.ego))
                        t0_us.append(frame.timestamp_us)
                        agent_poses.append(predictions[row["token"]])
                        pdm_poses.append(np.asarray(row["cache"]["pdm_closed_trajectory"])[:, 1:4])
                        expected_agent.append(row["diagnostics"]["pred_simulated"])
                        expected_pdm.append(row["diagnostics"]["pdm_simulated"])
        self.scenes = scenes
        self.labels = labels
        self.initial = np.array(initial)
        self.t0_us = np.array(t0_us)
        self.agent_poses = np.array(agent_poses, dtype=np.float64)
        self.pdm_poses = np.array(pdm_poses)
        self.agent_references = agent_references(self.initial, self.t0_us, self.agent_poses)
        self.pdm_references = pdm_references(self.t0_us, self.pdm_poses)
        # One batch: all PDM references, then all agent references.
        simulated = simulate(
            np.concatenate([self.pdm_references, self.agent_references]), np.concatenate([self.initial] * 2)
        )
        self.simulated_pdm, self.simulated_agent = np.split(simulated, 2)
        self.expected_pdm = np.array(expected_pdm)
        self.expected_agent = np.array(expected_agent)


@pytest.fixture(scope="module")
def cases() -> Cases:
    return Cases()


def _worst_differences(simulated: np.ndarray, expected: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    position = np.abs(simulated[..., :2] - expected[..., :2]).max(axis=(1, 2))
    heading = np.abs(normalize_angle(simulated[..., 2] - expected[..., 2])).max(axis=1)
    return position, heading


def test_every_reference_token_is_covered(cases: Cases) -> None:
    assert len(FAMILIES) == 13
    assert len(cases.labels) == 13 * 2 * 40
    assert cases.simulated_agent.shape == (len(cases.labels), 41, 11)


@pytest.mark.parametrize("proposal", ["agent", "pdm"])
def test_simulated_poses_match_the_devkit(cases: Cases, proposal: str) -> None:
    simulated = getattr(cases, f"simulated_{proposal}")[..., :3]
    expected = getattr(cases, f"expected_{proposal}")
    position, heading = _worst_differences(simulated, expected)
    failures = [
        f"{label}: position {p:.3g} m, heading {h:.3g} rad"
        for label, p, h in zip(cases.labels, position, heading, strict=True)
        if p > POSITION_TOLERANCE_M or h > HEADING_TOLERANCE_RAD
    ]
    assert failures == []


def test_straight_submissions_are_bit_exact(cases: Cases) -> None:
    """Without steering no transcendental last bit reaches the poses: these match the devkit exactly."""
    straight = [
        i for i, (family, _, _) in enumerate(cases.labels) if family in ("cv_straight", "stop", "reverse")
    ]
    simulated = cases.simulated_agent[straight, :, :3]
    assert np.array_equal(simulated, cases.expected_agent[straight])


def test_initial_row_is_the_round_tripped_ego(cases: Cases) -> None:
    assert np.array_equal(cases.simulated_agent[:, 0], cases.initial)
    assert np.array_equal(cases.simulated_pdm[:, 0], cases.initial)
    assert np.array_equal(cases.expected_agent[:, 0], cases.initial[:, :3])


def test_simulation_rows_do_not_depend_on_the_batch(cases: Cases) -> None:
    rows = [3, 500, 1039]
    alone = simulate(cases.agent_references[rows], cases.initial[rows])
    assert np.array_equal(alone, cases.simulated_agent[rows])
