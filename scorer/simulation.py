"""PDM's simulator: a batched LQR tracker driving a kinematic bicycle model over 4 s
(docs/engine.md, "Simulation").

Vectorised over proposals P; each row has its own reference and initial state, so proposals of many
tokens go through one call. Bit-exactness with the devkit depends on the arithmetic, so every
expression keeps NAVSIM's operand order, the fits keep its `pinv` (an SVD; a Cholesky solve rounds
differently) and its `einsum` wherever einsum's own summation order decides the result. The other
einsum calls of the devkit are written out as sums in exactly the order einsum adds them, which is
several times faster (tests check both claims against einsum).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from scorer.geometry import WHEEL_BASE, BoolArray, FloatArray, IntArray, normalize_angle, principal_value
from scorer.svml_tan import tan_avx512
from scorer.trajectory import SCORING_INTERVAL_S, SCORING_POSES, STATE_SIZE, StateIndex

# The tracker discretises with the proposal interval; the bicycle integrates over a TimePoint
# difference read back as `100000 * 1e-6`, one ulp below 0.1 (docs/engine.md,
# "Simulation: two time steps").
TRACKER_DT = SCORING_INTERVAL_S
BICYCLE_DT = 100_000 * 1e-6

# BatchLQRTracker defaults.
TRACKING_HORIZON = 10
LONGITUDINAL_Q = 10.0
LONGITUDINAL_R = 1.0
LATERAL_Q_DIAGONAL = np.array([1.0, 10.0, 0.0])  # Q = diag(1, 10, 0)
LATERAL_R = 1.0
JERK_PENALTY = 1e-4
CURVATURE_RATE_PENALTY = 1e-2
INITIAL_CURVATURE_PENALTY = 1e-10
STOPPING_GAIN = 0.5
STOPPING_VELOCITY = 0.2
# One-step longitudinal LQR (A = 1, B = horizon * dt, g = 0): accel = (-1 / (B q B + r)) * B * q * error,
# the leading factors multiplied in the devkit's order.
_LONGITUDINAL_B = TRACKING_HORIZON * TRACKER_DT
_LONGITUDINAL_INVERSE = -1 / (_LONGITUDINAL_B * LONGITUDINAL_Q * _LONGITUDINAL_B + LONGITUDINAL_R)
_LONGITUDINAL_GAIN = _LONGITUDINAL_INVERSE * _LONGITUDINAL_B * LONGITUDINAL_Q

# BatchKinematicBicycleModel defaults.
MAX_STEERING_ANGLE = np.pi / 3
ACCELERATION_TIME_CONSTANT = 0.2
STEERING_TIME_CONSTANT = 0.05

_DISPLACEMENTS = SCORING_POSES  # M displacements between the 41 reference poses


def _velocity_regulariser(num_displacements: int) -> FloatArray:
    """Return NAVSIM's (M-2, M) "jerk" regulariser, built wrongly as the devkit does.

    The banded difference block gets +1 on its superdiagonal and is then overwritten by -I, so only
    the last row keeps its +1: a ridge on the accelerations plus a single jerk term
    (docs/engine.md, "Simulation: the jerk regulariser").
    """
    rows = num_displacements - 2
    banded = np.zeros((rows, rows + 1))
    banded[:, 1:] = np.eye(rows)
    banded[:, :-1] = -np.eye(rows)
    return np.hstack([np.zeros((rows, 1)), banded])


_REGULARISER = _velocity_regulariser(_DISPLACEMENTS)
# Entries are small integers, so this product is exact however it is summed.
_VELOCITY_PENALTY = JERK_PENALTY * (_REGULARISER.T @ _REGULARISER)
_CURVATURE_PENALTY = CURVATURE_RATE_PENALTY * np.eye(_DISPLACEMENTS)
_CURVATURE_PENALTY[0, 0] = INITIAL_CURVATURE_PENALTY
# Acceleration unknowns only see displacements after them: zero the upper triangle, per row pair.
_UPPER_TRIANGLE = np.repeat(np.triu(np.ones((_DISPLACEMENTS, _DISPLACEMENTS), dtype=bool), k=1), 2, axis=0)
# The steering-angle row of the lateral input matrix after each horizon step: dt, dt + dt, ...
_STEERING_INPUT_SUMS = np.cumsum(np.full(TRACKING_HORIZON, TRACKER_DT))


def _batch_matmul(left: FloatArray, right: FloatArray) -> FloatArray:
    return np.einsum("bij, bjk -> bik", left, right)


def _tail_sums(terms: FloatArray) -> FloatArray:
    """Return s[..., m] = sum of terms[..., i, :] over i >= m, added in ascending (i, column) order.

    This is the order in which numpy's einsum accumulates `A^T A` for the transposed-view operands the
    devkit passes (one product after the other, no fused multiply-add), so the sums are bit-identical
    to the devkit's Gram matrices; `tests/test_simulation.py` checks that assumption against einsum.
    """
    sums = np.zeros(terms.shape[:-1], dtype=np.float64)
    for i in range(terms.shape[-2]):
        for column in range(terms.shape[-1]):
            sums[..., : i + 1] += terms[..., i, column, None]
    return sums


def _triangular_gram(first: FloatArray, rest: FloatArray) -> FloatArray:
    """Return `A^T A` (B, M, M) of a design whose row block i is `first[..., i]` in column 0 and `rest[..., i]`
    in columns 1..i (zero beyond), with row blocks of one or more rows (last axis of `first` and `rest`).

    Entry (j, k) only gets products from row blocks i >= max(j, k), and all columns >= 1 of a row hold the
    same value, so the Gram matrix is three families of tail sums instead of a dense product.
    """
    num = first.shape[1]
    tails = _tail_sums(np.stack([first * first, first * rest, rest * rest], axis=1))
    last = np.maximum.outer(np.arange(num), np.arange(num))
    gram = tails[:, 2][:, last]
    gram[:, 0, :] = tails[:, 1]
    gram[:, :, 0] = tails[:, 1]
    gram[:, 0, 0] = tails[:, 0, 0]
    return gram


def _integrate(initial: FloatArray, derivatives: FloatArray, dt: float) -> FloatArray:
    """Return [initial, initial + cumsum(derivatives * dt)] along the last axis (one value longer)."""
    cumulative = np.zeros((*derivatives.shape[:-1], derivatives.shape[-1] + 1))
    np.cumsum(derivatives * dt, axis=-1, out=cumulative[..., 1:])
    return initial[..., None] + cumulative


def reference_profiles(poses: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return the velocity and curvature profiles (P, M) fitted to reference poses (P, M + 1, 3).

    See docs/engine.md, "Simulation: reference profiles".
    """
    batch, num_displacements = poses.shape[0], poses.shape[1] - 1
    differences = np.diff(poses, axis=1)
    xy_displacements = differences[..., :2].reshape(batch, 2 * num_displacements)  # [dx_0, dy_0, dx_1, ...]
    heading_displacements = normalize_angle(differences[..., 2])

    # Velocity fit: unknowns v_0 and the accelerations a_0 .. a_{M-2}; displacement i (rows 2i, 2i + 1)
    # is dt * (cos h_i, sin h_i) * v_0 plus dt^2 * (cos h_i, sin h_i) * a_j for every j < i.
    headings = poses[:, :-1, 2]
    direction = np.stack([np.cos(headings), np.sin(headings)], axis=-1)
    interleaved = direction.reshape(batch, 2 * num_displacements)  # [cos h_0, sin h_0, cos h_1, ...]
    design = np.repeat(interleaved[..., None] * TRACKER_DT**2, num_displacements, axis=2)
    design[..., 0] = interleaved * TRACKER_DT
    design[:, _UPPER_TRIANGLE] = 0.0
    gram = _triangular_gram(direction * TRACKER_DT, direction * TRACKER_DT**2)
    solver = _batch_matmul(np.linalg.pinv(gram + _VELOCITY_PENALTY), np.transpose(design, (0, 2, 1)))
    solution = np.einsum("bij, bj -> bi", solver, xy_displacements)
    velocity = _integrate(solution[:, 0], solution[:, 1:], TRACKER_DT)

    # Curvature fit: unknowns kappa_0 and the curvature rates, given the fitted velocities.
    design = np.repeat(np.tri(num_displacements)[None], batch, axis=0)
    design[:, :, 0] = velocity * TRACKER_DT
    rate_column = velocity * TRACKER_DT**2
    design[:, 1:, 1:] *= rate_column[:, None, 1:].transpose(0, 2, 1)
    # Row 0 has no curvature-rate entries: its "rest" value is zero.
    rest = np.concatenate([np.zeros((batch, 1)), rate_column[:, 1:]], axis=1)
    gram = _triangular_gram((velocity * TRACKER_DT)[..., None], rest[..., None])
    solver = _batch_matmul(np.linalg.pinv(gram + _CURVATURE_PENALTY), design.transpose(0, 2, 1))
    solution = np.einsum("bij,bj->bi", solver, heading_displacements)
    curvature = _integrate(solution[:, 0], solution[:, 1:], TRACKER_DT)
    return velocity, curvature


def _previous(values: FloatArray) -> FloatArray:
    """Return the values one horizon step earlier, starting from 0 (the state before the first step)."""
    return np.concatenate([np.zeros((len(values), 1)), values[:, :-1]], axis=1)


def _lateral_error(
    lateral_state: FloatArray, velocities: FloatArray, curvatures: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return the one-step lateral LQR's error (B, 3) after the horizon, its heading error not yet wrapped, and
    the control (B, 2) that meets Q's non-zero weights (B0, B1).

    The devkit chains the step matrices S_i = I + (v_i dt) e_01 + (v_i dt / L) e_12 with einsum from
    A = I, B = 0, g = 0. Every row of S_i has at most two non-zero entries, so each entry of the chained
    A = [[1, a, b], [0, 1, c], [0, 0, 1]], B and g is a running sum of one product per step, which numpy's
    sequential `cumsum` rounds exactly as the einsum chain does (as it does the products with the
    diagonal Q). Only the 3-term product A x0 keeps einsum's own summation order
    (docs/engine.md, "Simulation: the tracker").
    """
    heading_gains = velocities * TRACKER_DT
    steering_gains = velocities * TRACKER_DT / WHEEL_BASE
    affine_terms = -velocities * curvatures * TRACKER_DT
    batch = len(lateral_state)

    steering_sums = np.cumsum(steering_gains, axis=1)  # c
    transition = np.zeros((batch, 3, 3))
    transition[:, [0, 1, 2], [0, 1, 2]] = 1.0
    transition[:, 0, 1] = np.cumsum(heading_gains, axis=1)[:, -1]
    transition[:, 0, 2] = np.cumsum(heading_gains * _previous(steering_sums), axis=1)[:, -1]
    transition[:, 1, 2] = steering_sums[:, -1]

    steering_inputs = np.broadcast_to(_STEERING_INPUT_SUMS, velocities.shape)  # B2: horizon steps of dt
    heading_inputs = np.cumsum(steering_gains * _previous(steering_inputs), axis=1)  # B1
    lateral_input = np.cumsum(heading_gains * _previous(heading_inputs), axis=1)[:, -1]  # B0
    heading_offsets = np.cumsum(affine_terms, axis=1)  # g1
    offset = np.zeros((batch, 3))
    offset[:, 0] = np.cumsum(heading_gains * _previous(heading_offsets), axis=1)[:, -1]
    offset[:, 1] = heading_offsets[:, -1]

    error = np.einsum("bij, bj -> bi", transition, lateral_state) + offset
    return error, np.stack([lateral_input, heading_inputs[:, -1]], axis=-1)  # B2 meets Q's zero weight


def _lateral_steering_rate(error: FloatArray, heading_error: FloatArray, control: FloatArray) -> FloatArray:
    """Return the one-step lateral LQR steering rate (B,) from `_lateral_error`'s error and control, the error's
    heading wrapped (`heading_error`). The devkit wraps the heading and the steering error; the steering error
    meets Q's zero weight and is never read, so only the heading error is wrapped."""
    weighted_control = control * LATERAL_Q_DIAGONAL[:2]  # B^T Q
    inverse = -1 / (
        weighted_control[:, 0] * control[:, 0] + weighted_control[:, 1] * control[:, 1] + LATERAL_R
    )
    return inverse * (weighted_control[:, 0] * error[:, 0] + weighted_control[:, 1] * heading_error)


class _Commands(NamedTuple):
    """A step's commands before the lateral LQR's heading error is wrapped (`_track`)."""

    stopping: BoolArray  # (P,) rows that take the stopping controller
    acceleration: FloatArray  # (P,)
    lateral_error: FloatArray  # (P, 3) the lateral LQR's error, its heading error (column 1) not yet wrapped
    lateral_control: FloatArray  # (P, 2)

    def steering_rate(self, heading_error: FloatArray) -> FloatArray:
        """Return the steering rate command (P,), given the lateral error's heading wrapped."""
        rate = _lateral_steering_rate(self.lateral_error, heading_error, self.lateral_control)
        return np.where(self.stopping, 0.0, rate)


def _track(
    states: FloatArray,
    target: FloatArray,
    heading_errors: FloatArray,
    reference_speed: FloatArray,
    curvature_window: FloatArray,
) -> _Commands:
    """Return the commands towards the reference pose `target`, the lateral one up to its heading error's wrap.

    `heading_errors` (P,) are the states' heading errors to the target, wrapped; `reference_speed` (P,) is the
    velocity profile at the lookahead index and `curvature_window` (P, 10) the curvature profile over the
    horizon. Proposals near standstill get the stopping controller (docs/engine.md, "Simulation: the tracker").
    """
    x_errors = states[:, StateIndex.X] - target[:, 0]
    y_errors = states[:, StateIndex.Y] - target[:, 1]
    lateral_errors = -x_errors * np.sin(target[:, 2]) + y_errors * np.cos(target[:, 2])
    speed = states[:, StateIndex.VELOCITY_X]
    lateral_state = np.stack([lateral_errors, heading_errors, states[:, StateIndex.STEERING_ANGLE]], axis=-1)

    # Both controllers run on every row (rows are independent); the mask picks one per row.
    stopping = (reference_speed <= STOPPING_VELOCITY) & (speed <= STOPPING_VELOCITY)
    stopping_acceleration = -STOPPING_GAIN * (speed - reference_speed)
    lqr_acceleration = _LONGITUDINAL_GAIN * (1.0 * speed + 0.0 - reference_speed)
    speeds = _integrate(speed, np.repeat(lqr_acceleration[:, None], TRACKING_HORIZON, axis=-1), TRACKER_DT)
    error, control = _lateral_error(lateral_state, speeds[:, :TRACKING_HORIZON], curvature_window)
    acceleration = np.where(stopping, stopping_acceleration, lqr_acceleration)
    return _Commands(stopping, acceleration, error, control)


def _next_heading(states: FloatArray, steering_tan: FloatArray) -> FloatArray:
    """Return the heading (P,) one bicycle step later, wrapped: it integrates the old speed, heading and steering
    angle (`steering_tan` its tan), so it is known before the step's commands."""
    speed = states[:, StateIndex.VELOCITY_X]
    return principal_value(states[:, StateIndex.HEADING] + speed * steering_tan / WHEEL_BASE * BICYCLE_DT)


def _propagate(
    states: FloatArray, heading: FloatArray, acceleration: FloatArray, steering_rate: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return the states (P, 11) one bicycle step of BICYCLE_DT later, and the tan of their steering angle.

    `heading` is their heading (`_next_heading`). Each step's yaw rate takes the tan of the angle the next
    step's heading takes it of, computed once (docs/engine.md, "Simulation: the bicycle model").
    """
    dt = BICYCLE_DT
    speed = states[:, StateIndex.VELOCITY_X]
    steering = states[:, StateIndex.STEERING_ANGLE]
    # First-order lags on the commanded acceleration and steering angle.
    ideal_steering = dt * steering_rate + steering
    current_acceleration = states[:, StateIndex.ACCELERATION_X]
    filtered_acceleration = (
        dt / (dt + ACCELERATION_TIME_CONSTANT) * (acceleration - current_acceleration) + current_acceleration
    )
    filtered_steering = dt / (dt + STEERING_TIME_CONSTANT) * (ideal_steering - steering) + steering
    filtered_steering_rate = (filtered_steering - steering) / dt

    result = np.empty_like(states)
    # Positions integrate with the old speed and heading (the heading with the old steering angle too).
    old_heading = states[:, StateIndex.HEADING]
    result[:, StateIndex.X] = states[:, StateIndex.X] + speed * np.cos(old_heading) * dt
    result[:, StateIndex.Y] = states[:, StateIndex.Y] + speed * np.sin(old_heading) * dt
    result[:, StateIndex.HEADING] = heading
    result[:, StateIndex.VELOCITY_X] = speed + filtered_acceleration * dt
    result[:, StateIndex.VELOCITY_Y] = 0.0
    result[:, StateIndex.ACCELERATION_X] = filtered_acceleration
    result[:, StateIndex.ACCELERATION_Y] = 0.0
    result[:, StateIndex.STEERING_ANGLE] = np.clip(
        steering + filtered_steering_rate * dt, -MAX_STEERING_ANGLE, MAX_STEERING_ANGLE
    )
    result[:, StateIndex.STEERING_RATE] = filtered_steering_rate
    result_tan = tan_avx512(result[:, StateIndex.STEERING_ANGLE])
    result[:, StateIndex.ANGULAR_VELOCITY] = result[:, StateIndex.VELOCITY_X] * result_tan / WHEEL_BASE
    result[:, StateIndex.ANGULAR_ACCELERATION] = (
        result[:, StateIndex.ANGULAR_VELOCITY] - states[:, StateIndex.ANGULAR_VELOCITY]
    ) / dt
    return result, result_tan


def simulate(reference: FloatArray, initial: FloatArray) -> FloatArray:
    """Return the simulated states (P, 41, 11) tracking reference poses (P, >=41, >=3) from `initial`.

    `initial` is one (11,) state shared by all proposals or one (P, 11) state per proposal; rows that repeat
    another's reference and initial state are simulated once (`_distinct_rows`). Raises ValueError when a
    reference is not finite or the simulation diverges to a non-finite heading (docs/engine.md, "Simulation").
    """
    reference = np.asarray(reference, dtype=np.float64)
    if reference.ndim != 3 or reference.shape[1] < SCORING_POSES + 1 or reference.shape[2] < 3:
        raise ValueError(f"reference: expected shape (P, >={SCORING_POSES + 1}, >=3), got {reference.shape}")
    poses = np.ascontiguousarray(reference[:, : SCORING_POSES + 1, :3])
    if not np.all(np.isfinite(poses)):
        rows = np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2))).tolist()
        raise ValueError(f"reference: non-finite pose in proposal row(s) {rows[:10]}")
    initial_states = np.broadcast_to(np.asarray(initial, dtype=np.float64), (len(poses), STATE_SIZE))
    distinct, inverse = _distinct_rows(poses, initial_states)
    if len(distinct) < len(poses):
        return _simulate(poses[distinct], initial_states[distinct])[inverse]
    return _simulate(poses, initial_states)


def _distinct_rows(poses: FloatArray, initial: FloatArray) -> tuple[IntArray, IntArray]:
    """Return one row of each distinct (poses, initial state) pair, and for every row its distinct one.

    Rows are compared byte for byte (so -0.0 and 0.0 differ, as they may in a simulation). Rows are
    independent (`simulate`), so a pair simulated once gives every copy's bits: metric versions whose
    PDM-Closed selects the same proposal, IDM proposals that coincide.
    """
    flat_poses = poses.reshape(len(poses), (SCORING_POSES + 1) * 3)  # simulate's (P, 41, 3)
    keys = np.ascontiguousarray(np.concatenate([flat_poses, initial], axis=1))
    rows = keys.view(np.dtype((np.void, keys.shape[1] * keys.itemsize))).reshape(-1)
    _, distinct, inverse = np.unique(rows, return_index=True, return_inverse=True)
    return distinct, inverse.reshape(-1)


def _simulate(poses: FloatArray, initial: FloatArray) -> FloatArray:
    """Return the simulated states (P, 41, 11) tracking finite reference poses (P, 41, 3) from `initial` (P, 11)."""
    batch = len(poses)
    states = np.zeros((batch, SCORING_POSES + 1, STATE_SIZE), dtype=np.float64)
    states[:, 0] = initial

    velocity, curvature = reference_profiles(poses)
    # Lookahead index min(k + 10, 39); the curvature window is padded with its value there.
    steps = np.arange(SCORING_POSES)
    lookahead = np.minimum(steps + TRACKING_HORIZON, velocity.shape[1] - 1)
    reference_speeds = velocity[:, lookahead]
    window_indices = np.minimum(steps[:, None] + np.arange(TRACKING_HORIZON), lookahead[:, None])
    curvature_windows = curvature[:, window_indices]
    steering_tan = tan_avx512(states[:, 0, StateIndex.STEERING_ANGLE])
    heading_errors = normalize_angle(states[:, 0, StateIndex.HEADING] - poses[:, 0, 2])
    for step in steps:
        state = states[:, step]
        commands = _track(
            state, poses[:, step], heading_errors, reference_speeds[:, step], curvature_windows[:, step]
        )
        # The next heading does not depend on this step's commands: its error to the next reference pose is
        # wrapped with this step's lateral heading error, in one arctan2 (elementwise: the same bits).
        heading = _next_heading(state, steering_tan)
        wrapped = normalize_angle(
            np.concatenate([commands.lateral_error[:, 1], heading - poses[:, step + 1, 2]])
        )
        heading_errors = wrapped[batch:]
        states[:, step + 1], steering_tan = _propagate(
            state, heading, commands.acceleration, commands.steering_rate(wrapped[:batch])
        )
    return states
