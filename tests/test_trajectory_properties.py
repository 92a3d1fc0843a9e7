"""Property tests for the frame transforms, the interpolation and the simulator."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from test_trajectory import global_to_relative

from scorer.geometry import normalize_angle, rear_axle_round_trip
from scorer.simulation import simulate
from scorer.trajectory import (
    StateIndex,
    interpolate_states,
    relative_to_global,
    scoring_times_us,
)

PROPERTY_SETTINGS = settings(max_examples=40, deadline=None)

coordinates = st.floats(-2e6, 2e6, allow_nan=False)
headings = st.floats(-math.pi, math.pi, allow_nan=False, exclude_max=True)
origins = st.tuples(coordinates, coordinates, headings).map(np.array)
relative_poses = arrays(
    np.float64,
    st.tuples(st.integers(1, 10), st.just(3)),
    elements=st.floats(-200.0, 200.0, allow_nan=False),
).map(lambda poses: np.column_stack([poses[:, :2], np.clip(poses[:, 2], -3.0, 3.0)]))
t0s = st.integers(1_500_000_000_000_000, 1_800_000_000_000_000)


@PROPERTY_SETTINGS
@given(origin=origins, poses=relative_poses)
def test_relative_to_global_and_back_is_the_identity(origin: np.ndarray, poses: np.ndarray) -> None:
    back = global_to_relative(origin, relative_to_global(origin, poses))
    # Global coordinates of up to 2e6 m carry ~2e-10 m of rounding.
    assert np.allclose(back[:, :2], poses[:, :2], rtol=0, atol=1e-8)
    assert np.all(np.abs(normalize_angle(back[:, 2] - poses[:, 2])) < 1e-12)


@PROPERTY_SETTINGS
@given(origin=origins, poses=relative_poses)
def test_relative_to_global_keeps_distances(origin: np.ndarray, poses: np.ndarray) -> None:
    absolute = relative_to_global(origin, poses)
    distances = np.hypot(absolute[:, 0] - origin[0], absolute[:, 1] - origin[1])
    assert np.allclose(distances, np.hypot(poses[:, 0], poses[:, 1]), rtol=0, atol=1e-8)


@PROPERTY_SETTINGS
@given(
    t0_us=t0s,
    steps=st.lists(st.integers(1, 600_000), min_size=1, max_size=12),
    seed=st.integers(0, 2**32 - 1),
)
def test_interpolation_reproduces_the_knots(t0_us: int, steps: list[int], seed: int) -> None:
    rng = np.random.default_rng(seed)
    knot_times = t0_us + np.concatenate([[0], np.cumsum(steps)])
    knots = np.zeros((len(knot_times), 11))
    knots[:, :2] = rng.uniform(-1e6, 1e6, 2) + rng.normal(0, 50, (len(knot_times), 2))
    knots[:, 2] = rng.uniform(-math.pi, math.pi, len(knot_times))
    knots[:, 3:8] = rng.normal(0, 5, (len(knot_times), 5))
    states = interpolate_states(knot_times[None], knots[None], knot_times[None])[0]
    x, y = rear_axle_round_trip(knots[:, 0], knots[:, 1], states[:, 2])
    assert np.allclose(states[:, 0], x, rtol=0, atol=1e-8)
    assert np.allclose(states[:, 1], y, rtol=0, atol=1e-8)
    assert np.all(np.abs(normalize_angle(states[:, 2] - knots[:, 2])) < 1e-9)
    assert np.allclose(states[:, 3:8], knots[:, 3:8], rtol=0, atol=1e-12)
    assert np.all(states[:, 8:] == 0.0)
    assert np.array_equal(states[0, 3:8], knots[0, 3:8])  # the first knot exactly


@PROPERTY_SETTINGS
@given(t0_us=t0s)
def test_query_times_are_at_most_one_microsecond_early(t0_us: int) -> None:
    offsets = scoring_times_us(t0_us) - (t0_us + 100_000 * np.arange(41))
    assert set(offsets.tolist()) <= {-1, 0}


def _straight_run(speed: float, heading: float, lateral_offset: float) -> tuple[np.ndarray, np.ndarray]:
    times = np.arange(41) * 0.1
    reference = np.zeros((1, 41, 3))
    reference[0, :, 0] = 5000.0 + speed * times * math.cos(heading)
    reference[0, :, 1] = -3000.0 + speed * times * math.sin(heading)
    reference[0, :, 2] = heading
    initial = np.zeros(11)
    initial[StateIndex.X] = 5000.0 - lateral_offset * math.sin(heading)
    initial[StateIndex.Y] = -3000.0 + lateral_offset * math.cos(heading)
    initial[StateIndex.HEADING] = heading
    initial[StateIndex.VELOCITY_X] = speed
    return reference, initial


@PROPERTY_SETTINGS
@given(speed=st.floats(1.0, 30.0), heading=headings)
def test_a_straight_constant_speed_reference_is_tracked(speed: float, heading: float) -> None:
    reference, initial = _straight_run(speed, heading, 0.0)
    states = simulate(reference, initial)[0]
    offsets = states[:, :2] - reference[0, :, :2]
    lateral = -offsets[:, 0] * math.sin(heading) + offsets[:, 1] * math.cos(heading)
    longitudinal = offsets[:, 0] * math.cos(heading) + offsets[:, 1] * math.sin(heading)
    assert np.max(np.abs(lateral)) < 1e-6
    assert np.max(np.abs(longitudinal)) < 0.05 * speed
    assert np.all(np.abs(normalize_angle(states[:, 2] - heading)) < 1e-6)


@PROPERTY_SETTINGS
@given(speed=st.floats(3.0, 25.0), heading=headings, offset=st.floats(-1.5, 1.5))
def test_a_lateral_offset_shrinks(speed: float, heading: float, offset: float) -> None:
    reference, initial = _straight_run(speed, heading, offset)
    states = simulate(reference, initial)[0]
    offsets = states[:, :2] - reference[0, :, :2]
    lateral = -offsets[:, 0] * math.sin(heading) + offsets[:, 1] * math.cos(heading)
    assert abs(lateral[-1]) <= abs(offset) * 0.6 + 1e-9
    assert np.max(np.abs(lateral)) <= abs(offset) * 1.05 + 1e-9


@PROPERTY_SETTINGS
@given(
    seed=st.integers(0, 2**32 - 1),
    speed=st.floats(0.0, 30.0),
    initial_speed=st.floats(0.0, 30.0),
    turn_rate=st.floats(-0.6, 0.6),
)
def test_simulation_stays_finite_with_wrapped_headings(
    seed: int, speed: float, initial_speed: float, turn_rate: float
) -> None:
    rng = np.random.default_rng(seed)
    heading = rng.uniform(-math.pi, math.pi) + turn_rate * np.arange(41) * 0.1 + rng.normal(0, 0.05, 41)
    steps = speed * 0.1 * np.column_stack([np.cos(heading), np.sin(heading)]) + rng.normal(0, 0.1, (41, 2))
    reference = np.zeros((1, 41, 3))
    reference[0, :, :2] = np.cumsum(steps, axis=0) - steps[0]
    reference[0, :, 2] = normalize_angle(heading)
    initial = np.zeros(11)
    initial[StateIndex.HEADING] = reference[0, 0, 2]
    initial[StateIndex.VELOCITY_X] = initial_speed
    states = simulate(reference, initial)[0]
    assert np.all(np.isfinite(states))
    assert np.all((states[:, 2] >= -math.pi) & (states[:, 2] < math.pi))
    assert np.all(np.abs(states[:, StateIndex.STEERING_ANGLE]) <= math.pi / 3)
