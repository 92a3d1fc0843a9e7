"""Trajectories as the devkit samples them for scoring: global frame, 41 states at 10 Hz.

The devkit turns every pose into a nuPlan `EgoState`, interpolates an `InterpolatedTrajectory` with
scipy's `interp1d` at integer-microsecond query times, and reads the states back. Each of those steps
moves the last bits (rear-axle round trip, truncated time stamps, unwrap over the knots), and the last
bits decide knife-edge metrics, so this module reproduces the arithmetic rather than the idea
(docs/engine.md, "Sampling" and "Time stamps").
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
import numpy.typing as npt

from scorer.geometry import FloatArray, arctan2_avx512, principal_value, rear_axle_round_trip
from scorer.scene import EgoStatus

# Time stamps in us since the epoch (~1.6e15), int64 on every platform, as the devkit's integer TimePoints;
# not geometry.IntArray (np.intp, indices and counts), which is 32 bits on a 32-bit build.
MicrosecondArray = npt.NDArray[np.int64]


class StateIndex(IntEnum):
    """Columns of a state array (PDM's `StateIndex`): rear axle, global pose, ego-frame dynamics.

    See docs/engine.md, "Conventions: state arrays".
    """

    X = 0
    Y = 1
    HEADING = 2
    VELOCITY_X = 3
    VELOCITY_Y = 4
    ACCELERATION_X = 5
    ACCELERATION_Y = 6
    STEERING_ANGLE = 7
    STEERING_RATE = 8
    ANGULAR_VELOCITY = 9
    ANGULAR_ACCELERATION = 10


STATE_SIZE = len(StateIndex)
SCORING_POSES = 40  # proposal_sampling of the scoring yaml: 40 poses at 0.1 s after the initial state
SCORING_INTERVAL_S = 0.1
PDM_KNOT_INTERVAL_US = 100_000  # the cached PDM-Closed trajectory: 51 states at t0 + k * 0.1 s

# Channels an EgoState interpolates linearly (to_split_state order): x, y, vx, vy, ax, ay, steering angle.
_LINEAR_COLUMNS = [
    StateIndex.X,
    StateIndex.Y,
    StateIndex.VELOCITY_X,
    StateIndex.VELOCITY_Y,
    StateIndex.ACCELERATION_X,
    StateIndex.ACCELERATION_Y,
    StateIndex.STEERING_ANGLE,
]


def initial_state(ego: EgoStatus) -> FloatArray:
    """Return the (11,) state array of the initial EgoState (rear axle after the round trip).

    See docs/engine.md, "Simulation" and "Conventions: the rear-axle round trip".
    """
    x, y = rear_axle_round_trip(ego.x, ego.y, ego.heading)
    state = np.zeros(STATE_SIZE, dtype=np.float64)
    state[: StateIndex.ACCELERATION_Y + 1] = (x, y, ego.heading, ego.vx, ego.vy, ego.ax, ego.ay)
    return state


def scoring_times_us(t0_us: int | MicrosecondArray) -> MicrosecondArray:
    """Return the 41 query times in us (..., 41), before clipping: `int((arange + t0 * 1e-6) * 1e6)`.

    See docs/engine.md, "Time stamps".
    """
    times_s = np.arange(0.0, SCORING_POSES * SCORING_INTERVAL_S + SCORING_INTERVAL_S, SCORING_INTERVAL_S)
    return _truncate_to_us(times_s + _seconds(t0_us))


def agent_knot_times_us(
    t0_us: int | MicrosecondArray, num_poses: int, interval_length: float
) -> MicrosecondArray:
    """Return the time stamps (..., n) of submitted poses as nuPlan's `_get_fixed_timesteps` makes them.

    See docs/engine.md, "Time stamps".
    """
    steps_s = np.arange(0.0, num_poses * interval_length, interval_length) + interval_length
    return _truncate_to_us(steps_s[:num_poses] + _seconds(t0_us))


def _seconds(t0_us: int | MicrosecondArray) -> FloatArray:
    # TimePoint.time_s is a multiplication (a TimeDuration would divide).
    seconds: FloatArray = np.asarray(t0_us, dtype=np.int64) * 1e-6
    return seconds[..., None]


def _truncate_to_us(times_s: FloatArray) -> MicrosecondArray:
    # `int(t * 1e6)` truncates, which puts many stamps 1 us early.
    return (times_s * 1e6).astype(np.int64)


def relative_to_global(origin: FloatArray, poses: FloatArray) -> FloatArray:
    """Return poses (..., n, 3) given in the frame of `origin` (..., 3) in the global frame.

    As nuPlan's `relative_to_absolute_poses`: numpy's matmul of 3x3 homogeneous matrices, heading read
    back with atan2.
    """
    return _poses_of(_pose_matrices(origin)[..., None, :, :] @ _pose_matrices(poses))


def global_to_relative(poses: FloatArray) -> FloatArray:
    """Return poses (..., n, 3) in the frame of the first pose of each sequence (the first becomes zeros).

    As nuPlan's `absolute_to_relative_poses`: the origin's matrix inverted with `np.linalg.inv` (LAPACK, so
    its last bits are the host's, like every BLAS call the devkit makes: docs/engine.md, "BLAS"), numpy's
    matmul, heading read back with atan2.
    """
    matrices = _pose_matrices(poses)
    return _poses_of(np.linalg.inv(matrices[..., :1, :, :]) @ matrices)


def _pose_matrices(poses: FloatArray) -> FloatArray:
    cos_h, sin_h = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    matrices = np.zeros((*poses.shape[:-1], 3, 3), dtype=np.float64)
    matrices[..., 0, 0], matrices[..., 0, 1], matrices[..., 0, 2] = cos_h, -sin_h, poses[..., 0]
    matrices[..., 1, 0], matrices[..., 1, 1], matrices[..., 1, 2] = sin_h, cos_h, poses[..., 1]
    matrices[..., 2, 2] = 1.0
    return matrices


def _poses_of(matrices: FloatArray) -> FloatArray:
    headings = arctan2_avx512(matrices[..., 1, 0], matrices[..., 0, 0])
    return np.stack([matrices[..., 0, 2], matrices[..., 1, 2], headings], axis=-1)


def agent_references(
    initial: FloatArray, t0_us: MicrosecondArray, poses: FloatArray, interval_length: float = 0.5
) -> FloatArray:
    """Return the reference states (T, 41, 11) of T submitted trajectories, each with its own initial state.

    `initial` (T, 11) are initial states (`initial_state`), `t0_us` (T,) the current time stamps and
    `poses` (T, n, 3) the submitted poses in each ego frame. Knot 0 is the initial state with its measured
    dynamics; the poses follow at `interval_length` steps with zero dynamics, each as an EgoState (so
    after the rear-axle round trip).
    """
    initial = np.asarray(initial, dtype=np.float64)
    absolute = relative_to_global(initial[:, : StateIndex.HEADING + 1], np.asarray(poses, dtype=np.float64))
    knots = np.zeros((len(initial), absolute.shape[1] + 1, STATE_SIZE), dtype=np.float64)
    knots[:, 0] = initial
    knots[:, 1:, StateIndex.X], knots[:, 1:, StateIndex.Y] = rear_axle_round_trip(
        absolute[..., 0], absolute[..., 1], absolute[..., 2]
    )
    knots[:, 1:, StateIndex.HEADING] = absolute[..., 2]
    t0_us = np.asarray(t0_us, dtype=np.int64)
    knot_times = np.concatenate(
        [t0_us[:, None], agent_knot_times_us(t0_us, absolute.shape[1], interval_length)], axis=1
    )
    return interpolate_states(knot_times, knots, scoring_times_us(t0_us))


def pdm_references(t0_us: MicrosecondArray, pdm_poses: FloatArray) -> FloatArray:
    """Return the reference states (T, 41, 11) of T cached PDM-Closed trajectories (T, 51, 3).

    The poses are those the cached EgoStates report (already round-tripped) at t0 + k * 0.1 s; their
    dynamics are zero (docs/engine.md, "Sampling").
    """
    pdm_poses = np.asarray(pdm_poses, dtype=np.float64)
    knots = np.zeros((*pdm_poses.shape[:-1], STATE_SIZE), dtype=np.float64)
    knots[..., : StateIndex.HEADING + 1] = pdm_poses
    t0_us = np.asarray(t0_us, dtype=np.int64)
    knot_times = t0_us[:, None] + PDM_KNOT_INTERVAL_US * np.arange(pdm_poses.shape[1], dtype=np.int64)
    return interpolate_states(knot_times, knots, scoring_times_us(t0_us))


def interpolate_states(
    knot_times_us: MicrosecondArray, knots: FloatArray, query_times_us: MicrosecondArray
) -> FloatArray:
    """Return states (T, q, 11) of T InterpolatedTrajectories with knots (T, k, 11) at (T, q) times.

    Query times are clipped to each knot span. Linear channels use scipy `interp1d`'s formula; the heading
    is unwrapped over the knots, interpolated and wrapped to [-pi, pi); the result is rebuilt as an
    EgoState, so x, y go through the rear-axle round trip and the rates read back as zero
    (docs/engine.md, "Sampling").
    """
    queries = np.clip(query_times_us, knot_times_us[:, :1], knot_times_us[:, -1:])
    # interp1d: the knot interval comes from searchsorted (side left), clipped to [1, k - 1].
    upper = (knot_times_us[:, None, :] < queries[:, :, None]).sum(axis=-1)
    upper = np.clip(upper, 1, knot_times_us.shape[1] - 1)
    lower = upper - 1
    # Integer differences are exact, as scipy's float64 view of the same integer stamps is.
    low_times = np.take_along_axis(knot_times_us, lower, axis=1)
    span = (np.take_along_axis(knot_times_us, upper, axis=1) - low_times).astype(np.float64)[..., None]
    offset = (queries - low_times).astype(np.float64)[..., None]

    headings = np.unwrap(knots[..., StateIndex.HEADING], axis=-1)[..., None]
    values = np.concatenate([knots[..., _LINEAR_COLUMNS], headings], axis=-1)
    low = np.take_along_axis(values, lower[..., None], axis=1)
    high = np.take_along_axis(values, upper[..., None], axis=1)
    interpolated = (high - low) / span * offset + low

    states = np.zeros((*queries.shape, STATE_SIZE), dtype=np.float64)
    heading = principal_value(interpolated[..., -1])
    states[..., StateIndex.X], states[..., StateIndex.Y] = rear_axle_round_trip(
        interpolated[..., 0], interpolated[..., 1], heading
    )
    states[..., StateIndex.HEADING] = heading
    states[..., _LINEAR_COLUMNS[2:]] = interpolated[..., 2:-1]
    return states
