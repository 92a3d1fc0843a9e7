"""Trajectory sampling: time stamps, frame transform and interpolation as the devkit computes them."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.interpolate import interp1d

from scorer.geometry import principal_value, rear_axle_round_trip
from scorer.scene import EgoStatus
from scorer.trajectory import (
    StateIndex,
    agent_knot_times_us,
    agent_references,
    initial_state,
    interpolate_states,
    pdm_references,
    relative_to_global,
    scoring_times_us,
)

EGO = EgoStatus(x=664_000.25, y=3_996_000.75, heading=2.9, vx=7.5, vy=0.125, ax=-0.5, ay=0.25)
T0_US = 1_630_000_000_123_457


def global_to_relative(origin: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """The inverse transform, written independently: subtract the origin, rotate by minus its heading."""
    cos_h, sin_h = math.cos(origin[2]), math.sin(origin[2])
    dx, dy = poses[..., 0] - origin[0], poses[..., 1] - origin[1]
    heading = principal_value(poses[..., 2] - origin[2])
    return np.stack([cos_h * dx + sin_h * dy, -sin_h * dx + cos_h * dy, heading], axis=-1)


def agent_reference(poses: np.ndarray) -> np.ndarray:
    """The reference states of one submitted trajectory from EGO at T0_US."""
    return agent_references(initial_state(EGO)[None], np.array([T0_US]), poses[None])[0]


def test_query_times_are_truncated_like_the_devkit() -> None:
    """Spec 1.3's example: queries 1, 6, 11, ... land 1 us early."""
    offsets = scoring_times_us(T0_US) - (T0_US + 100_000 * np.arange(41))
    assert offsets[:12].tolist() == [0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1]
    assert set(offsets.tolist()) == {0, -1}


def test_time_stamps_of_many_tokens_equal_those_of_each() -> None:
    t0 = np.array([T0_US, 1_700_000_000_000_001, 12_345])
    assert np.array_equal(scoring_times_us(t0), np.stack([scoring_times_us(t) for t in t0]))
    knots = agent_knot_times_us(t0, 8, 0.5)
    assert knots.shape == (3, 8)
    assert np.array_equal(knots[1], agent_knot_times_us(int(t0[1]), 8, 0.5))
    assert np.all(np.abs(knots - t0[:, None] - 500_000 * np.arange(1, 9)) <= 1)


def test_initial_state_is_the_round_tripped_ego() -> None:
    state = initial_state(EGO)
    assert state.shape == (11,)
    assert (state[0], state[1]) == tuple(float(v) for v in rear_axle_round_trip(EGO.x, EGO.y, EGO.heading))
    assert state[2:7].tolist() == [EGO.heading, EGO.vx, EGO.vy, EGO.ax, EGO.ay]
    assert state[7:].tolist() == [0.0, 0.0, 0.0, 0.0]


def test_relative_to_global_rotates_then_translates() -> None:
    origin = np.array([10.0, 5.0, math.pi / 2])
    poses = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, math.pi / 2]])
    result = relative_to_global(origin, poses)
    assert np.allclose(result, [[10.0, 6.0, math.pi / 2], [8.0, 5.0, math.pi]], atol=1e-12)
    assert np.allclose(global_to_relative(origin, result), poses, atol=1e-12)


def _scipy_states(knot_times: np.ndarray, knots: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """The devkit's InterpolatedTrajectory on the same knots: interp1d, unwrap, principal value, EgoState."""
    linear = [StateIndex.X, StateIndex.Y, 3, 4, 5, 6, 7]
    times = knot_times.tolist()  # the devkit interpolates over a list of integer time stamps
    clipped = np.clip(queries, knot_times[0], knot_times[-1]).tolist()
    values = interp1d(times, knots[:, linear], axis=0)(clipped)
    heading = principal_value(interp1d(times, np.unwrap(knots[:, [2]], axis=0), axis=0)(clipped)[:, 0])
    states = np.zeros((len(queries), 11))
    states[:, 0], states[:, 1] = rear_axle_round_trip(values[:, 0], values[:, 1], heading)
    states[:, 2] = heading
    states[:, 3:8] = values[:, 2:]
    return states


@pytest.mark.parametrize("seed", range(6))
def test_interpolation_equals_scipy_interp1d_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    count = int(rng.integers(2, 12))
    knot_times = T0_US + np.cumsum(rng.integers(1, 600_000, count))
    knots = np.zeros((count, 11))
    knots[:, :2] = rng.uniform(-1e6, 1e6, 2) + rng.normal(0, 30, (count, 2))
    knots[:, 2] = principal_value(np.cumsum(rng.normal(0, 2.0, count)))  # wraps, so unwrap matters
    knots[:, 3:8] = rng.normal(0, 3, (count, 5))
    queries = rng.integers(knot_times[0] - 50_000, knot_times[-1] + 50_000, 41)
    queries[:count] = knot_times  # exactly at the knots too
    ours = interpolate_states(knot_times[None], knots[None], queries[None])[0]
    assert np.array_equal(ours, _scipy_states(knot_times, knots, queries))


def test_agent_reference_starts_at_the_ego_and_passes_the_submitted_poses() -> None:
    poses = np.column_stack([np.linspace(4, 32, 8), np.linspace(0.2, 3.0, 8), np.linspace(0.02, 0.3, 8)])
    reference = agent_reference(poses)
    assert reference.shape == (41, 11)
    assert np.allclose(reference[0], initial_state(EGO), rtol=0, atol=1e-9)
    expected = relative_to_global(initial_state(EGO)[:3], poses)
    # Knots are 0.5 s apart; a query 1 us early moves a pose by about speed * 1e-6 m.
    assert np.allclose(reference[5::5, :3], expected, rtol=0, atol=1e-4)
    # Dynamics fade from the measured ones at t0 to zero at the first submitted pose.
    assert reference[0, StateIndex.VELOCITY_X] == EGO.vx
    assert np.all(reference[5:, 3:] == 0.0)
    assert np.all((reference[:, 2] >= -math.pi) & (reference[:, 2] < math.pi))


def test_a_short_horizon_repeats_its_last_pose() -> None:
    poses = np.array([[2.0, 0.0, 0.0], [4.0, 0.0, 0.0]])  # 1 s at 0.5 s
    reference = agent_reference(poses)
    assert np.array_equal(reference[11:], np.repeat(reference[10:11], 30, axis=0))


def test_pdm_reference_samples_its_knots() -> None:
    pdm_poses = np.column_stack([EGO.x + np.arange(51.0), np.full(51, EGO.y), np.full(51, 0.1)])
    reference = pdm_references(np.array([T0_US]), pdm_poses[None])[0]
    assert reference.shape == (41, 11)
    assert np.allclose(reference[:, :3], pdm_poses[:41], rtol=0, atol=1e-5)
    assert np.all(reference[:, 3:] == 0.0)
