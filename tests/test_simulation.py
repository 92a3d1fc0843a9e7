"""The LQR tracker and kinematic bicycle: written-out sums equal the devkit's einsum, controller facts, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scorer import simulation
from scorer.geometry import arctan2_avx512, normalize_angle
from scorer.simulation import (
    _LONGITUDINAL_GAIN,
    _REGULARISER,
    _UPPER_TRIANGLE,
    _lateral_error,
    _lateral_steering_rate,
    _triangular_gram,
    simulate,
)
from scorer.trajectory import StateIndex

DT = 0.1


def _velocity_design(headings: np.ndarray) -> np.ndarray:
    """The velocity fit's design matrix (B, 2M, M), as spec 2.2 builds it."""
    batch, num = headings.shape
    column = np.zeros((batch, 2 * num))
    column[:, 0::2], column[:, 1::2] = np.cos(headings), np.sin(headings)
    design = np.repeat(column[..., None] * DT**2, num, axis=2)
    design[..., 0] = column * DT
    design[:, _UPPER_TRIANGLE] = 0.0
    return design


def _curvature_design(velocity: np.ndarray) -> np.ndarray:
    """The curvature fit's design matrix (B, M, M), as spec 2.2 builds it."""
    batch, num = velocity.shape
    design = np.repeat(np.tri(num)[None], batch, axis=0)
    design[:, :, 0] = velocity * DT
    design[:, 1:, 1:] *= (velocity * DT**2)[:, None, 1:].transpose(0, 2, 1)
    return design


def _einsum_gram(design: np.ndarray) -> np.ndarray:
    return np.einsum("bij, bjk -> bik", np.transpose(design, (0, 2, 1)), design)


@pytest.mark.parametrize("batch", [1, 3, 64])
def test_velocity_gram_equals_einsum_bit_for_bit(batch: int) -> None:
    headings = np.random.default_rng(batch).uniform(-math.pi, math.pi, (batch, 40))
    direction = np.stack([np.cos(headings), np.sin(headings)], axis=-1)
    gram = _triangular_gram(direction * DT, direction * DT**2)
    assert np.array_equal(gram, _einsum_gram(_velocity_design(headings)))


@pytest.mark.parametrize("batch", [1, 3, 64])
def test_curvature_gram_equals_einsum_bit_for_bit(batch: int) -> None:
    velocity = np.random.default_rng(batch).normal(8.0, 6.0, (batch, 40))  # negative speeds too
    rest = np.concatenate([np.zeros((batch, 1)), velocity[:, 1:] * DT**2], axis=1)
    gram = _triangular_gram((velocity * DT)[..., None], rest[..., None])
    assert np.array_equal(gram, _einsum_gram(_curvature_design(velocity)))


def _einsum_lateral_steering_rate(
    state: np.ndarray, velocities: np.ndarray, curvatures: np.ndarray
) -> np.ndarray:
    """Spec 2.3's lateral LQR with the 3x3 chain in einsum, as the devkit computes it."""
    batch, horizon = velocities.shape
    steps = np.tile(np.eye(3)[None, None], [horizon, batch, 1, 1])
    steps[:, :, 0, 1] = velocities.T * DT
    steps[:, :, 1, 2] = velocities.T * DT / 3.089
    affine = np.zeros((horizon, batch, 3))
    affine[:, :, 1] = -velocities.T * curvatures.T * DT
    transition, control, offset = (
        np.tile(np.eye(3)[None], [batch, 1, 1]),
        np.zeros((batch, 3, 1)),
        np.zeros((batch, 3)),
    )
    for step, term in zip(steps, affine, strict=True):
        transition = np.einsum("bij, bjk -> bik", step, transition)
        control = np.einsum("bij, bjk -> bik", step, control) + np.array([[0.0], [0.0], [DT]])
        offset = np.einsum("bij, bj  -> bi", step, offset) + term
    error = np.einsum("bij, bj -> bi", transition, state) + offset
    # The devkit's arctan2 as it ran for the official results (numpy's AVX-512 one), on every host.
    error[:, 1:] = arctan2_avx512(np.sin(error[:, 1:]), np.cos(error[:, 1:]))
    weighted = np.einsum("bij, jk -> bik", control.transpose(0, 2, 1), np.diag([1.0, 10.0, 0.0]))
    inverse = -1 / (np.einsum("bij, bji -> bi", weighted, control) + np.diag([1.0]))
    return (inverse * np.einsum("bij, bj -> bi", weighted, error))[:, 0]


@pytest.mark.parametrize("seed", range(4))
def test_lateral_lqr_equals_the_einsum_chain_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    batch = 50
    state = rng.normal(0, [1.0, 0.5, 0.3], (batch, 3))
    velocities = rng.normal(8, 8, (batch, 1)) + np.cumsum(rng.normal(0, 0.3, (batch, 10)), axis=1)
    curvatures = rng.normal(0, 0.05, (batch, 10))
    error, control = _lateral_error(state, velocities, curvatures)
    ours = _lateral_steering_rate(error, normalize_angle(error[:, 1]), control)
    assert np.array_equal(ours, _einsum_lateral_steering_rate(state, velocities, curvatures))


def test_velocity_regulariser_is_the_devkit_s_wrong_band() -> None:
    """Pitfall 26: -1 at column r + 1 in every row, +1 only in the last row's last column."""
    assert _REGULARISER.shape == (38, 40)
    expected = np.zeros((38, 40))
    expected[np.arange(38), np.arange(1, 39)] = -1.0
    expected[37, 39] = 1.0
    assert np.array_equal(_REGULARISER, expected)


def test_longitudinal_lqr_worked_example() -> None:
    """Spec 2.3: v = 8, v_ref = 10 gives (-1/11) * 1 * 10 * (-2) = 1.818 m/s^2."""
    assert _LONGITUDINAL_GAIN * (8.0 - 10.0) == pytest.approx(20.0 / 11.0, rel=1e-15)


def _straight_reference(speed: float, heading: float, count: int = 1) -> tuple[np.ndarray, np.ndarray]:
    times = np.arange(41) * 0.1
    reference = np.zeros((count, 41, 11))
    reference[..., 0] = 100.0 + speed * times * math.cos(heading)
    reference[..., 1] = -50.0 + speed * times * math.sin(heading)
    reference[..., 2] = heading
    initial = np.zeros(11)
    initial[[0, 1, 2, 3]] = [100.0, -50.0, heading, speed]
    return reference, initial


def test_a_stopped_ego_with_a_stopped_reference_stays_put() -> None:
    reference, initial = _straight_reference(0.0, 0.4)
    states = simulate(reference, initial)[0]
    assert np.all(states[:, :2] == initial[:2])
    # Wrapping to [-pi, pi) by floor-mod after every step may move the heading by an ulp, as in the devkit.
    assert np.allclose(states[:, 2], initial[2], rtol=0, atol=1e-15)
    assert np.all(states[:, 3:] == 0.0)


def test_bicycle_uses_the_timepoint_step_and_writes_zero_lateral_dynamics() -> None:
    reference, initial = _straight_reference(10.0, 0.0)
    initial[StateIndex.VELOCITY_Y] = 0.3
    initial[StateIndex.ACCELERATION_Y] = 0.7
    states = simulate(reference, initial)[0]
    assert states[0, StateIndex.ACCELERATION_Y] == 0.7  # index 0 keeps the measured values
    assert np.all(states[1:, StateIndex.VELOCITY_Y] == 0.0)
    assert np.all(states[1:, StateIndex.ACCELERATION_Y] == 0.0)
    # First step: x advances by v * cos(h) * dt with dt = 100000 * 1e-6, one ulp below 0.1.
    assert states[1, StateIndex.X] == 100.0 + 10.0 * math.cos(0.0) * (100_000 * 1e-6)


def test_one_initial_state_or_one_per_row_give_the_same_result() -> None:
    reference, initial = _straight_reference(6.0, -2.0, count=3)
    reference[1, :, 1] += np.linspace(0, 2, 41)  # a lateral drift for variety
    assert np.array_equal(simulate(reference, initial), simulate(reference, np.tile(initial, (3, 1))))


def test_rows_are_independent_of_the_batch() -> None:
    reference, initial = _straight_reference(12.0, 1.0, count=4)
    reference[2, :, 0] += np.linspace(0, 3, 41) ** 2
    together = simulate(reference, initial)
    for row in range(4):
        assert np.array_equal(simulate(reference[row : row + 1], initial)[0], together[row])


def test_a_repeated_row_is_simulated_once_and_its_copies_are_its_bits(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    reference, initial = _straight_reference(8.0, 0.5, count=3)
    reference[1, :, 1] += np.linspace(0, 1, 41)
    reference[0, 0, 2], reference[2, 0, 2] = 0.0, -0.0  # rows 0 and 2 differ in a zero's sign only: two rows
    simulated_rows: list[int] = []
    run = simulation._simulate

    def counted(poses: np.ndarray, initial: np.ndarray) -> np.ndarray:
        simulated_rows.append(len(poses))
        return run(poses, initial)

    monkeypatch.setattr(simulation, "_simulate", counted)
    together = simulate(reference[[0, 1, 0, 2, 1, 0]], initial)
    assert simulated_rows == [3]
    for index, row in enumerate([0, 1, 0, 2, 1, 0]):
        assert np.array_equal(together[index], simulate(reference[row : row + 1], initial)[0])


def test_extra_poses_and_columns_are_ignored() -> None:
    reference, initial = _straight_reference(5.0, 0.5)
    longer = np.concatenate([reference, reference[:, -10:]], axis=1)
    assert np.array_equal(simulate(longer, initial), simulate(reference[..., :3], initial))


def test_non_finite_reference_names_the_rows() -> None:
    reference, initial = _straight_reference(5.0, 0.5, count=3)
    reference[2, 7, 1] = np.nan
    with pytest.raises(ValueError, match=r"non-finite pose in proposal row\(s\) \[2\]"):
        simulate(reference, initial)


def test_wrong_reference_shape_is_refused() -> None:
    with pytest.raises(ValueError, match="expected shape"):
        simulate(np.zeros((2, 30, 3)), np.zeros(11))


def test_a_diverging_simulation_raises_instead_of_returning_nan() -> None:
    reference, initial = _straight_reference(5.0, 0.5)
    initial[StateIndex.VELOCITY_X] = np.inf
    with np.errstate(all="ignore"), pytest.raises(ValueError, match="non-finite heading"):
        simulate(reference, initial)


def test_an_empty_batch_is_fine() -> None:
    assert simulate(np.zeros((0, 41, 3)), np.zeros(11)).shape == (0, 41, 11)
