"""History comfort (HC) in {0, 1}, a weighted metric of v2.2: comfort of the logged past joined to the
simulated future (docs/engine.md, "Comfort filters").

The metric cache holds the human past as `InterpolatedTrajectory(get_ego_past_trajectory(0, 1.5))`: the
EgoStates of frames current-3 ... current (NAVSIM's `sample_past_indices`; tire steering angle 0, the
frames' float32 velocities and accelerations). `_calculate_history_comfort` samples it at the integer
microsecond times `arange(t_-3, t_0, 100_000)[:-1]`, i.e. t_-1.5 ... t_-0.2 s, 14 states when the frames
are 0.5 s apart and 15 when they are a little further apart, with the same interpolation as the scored
trajectories (`trajectory.interpolate_states`: linear channels, heading unwrapped, EgoStates rebuilt from
the rear axle, so the rates are 0). It prepends them to every simulated proposal and runs v2.2's comfort
functions on the whole series as if it were spaced 0.1 s throughout, although 0.2 s separate its last
past state from the initial state. All states must pass all six checks.

The devkit runs one `ego_is_comfortable` per `score_proposals` call (in evaluation PDM-Closed's reference
and the submission share it), so a token's proposals are one filter group (`comfort.filtered_as_devkit`).
Calls without a past (the human of the penalty filter, PDM-Closed ranking its proposals) score 1.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from scorer.geometry import BoolArray, FloatArray
from scorer.metrics.comfort import CHECKS, V2_2_WINDOWS, comfort_checks, comfort_series
from scorer.scene import Scene
from scorer.trajectory import SCORING_INTERVAL_S, initial_state, interpolate_states

PAST_FRAMES = 3  # `get_ego_past_trajectory(0, 1.5)` at the 0.5 s database interval: iterations -3 ... 0
PAST_STEP_US = 100_000  # `int(0.1 * 1e6)`


def past_states(scene: Scene) -> FloatArray:
    """Return the human past states (n_past, 11) the devkit prepends, at t_-3 + k * 0.1 s before t_0
    without the last of those times.

    Raises ValueError where the devkit fails: fewer than 3 frames before the current one, or no state to
    sample (the past frames span at most 0.1 s).
    """
    first = scene.current_index - PAST_FRAMES
    if first < 0:
        raise ValueError(f"history comfort needs {PAST_FRAMES} past frames, scene has {scene.current_index}")
    frames = scene.frames[first : scene.current_index + 1]
    knot_times = np.array([frame.timestamp_us for frame in frames], dtype=np.int64)
    times = np.arange(knot_times[0], knot_times[-1], PAST_STEP_US, dtype=np.int64)[:-1]
    if len(times) == 0:
        raise ValueError(f"no past state to sample between {knot_times[0]} and {knot_times[-1]} us")
    knots = np.stack([initial_state(frame.ego) for frame in frames])
    return interpolate_states(knot_times[None], knots[None], times[None])[0]


def history_comfort_checks(series: FloatArray, pasts: Sequence[FloatArray | None]) -> BoolArray:
    """Return the six checks (B, P, 6) in `comfort.CHECKS` order of B tokens' simulated proposals, from their
    `comfort_series(states, at_centre=True)` (B, P, 41, c), each token's proposals filtered as one group after
    the series of its `past_states` (n_past, 11); all True for a token whose past is None.

    The series of a state depends on that state alone, so the past's series joins the proposals' unchanged.
    Tokens may have pasts of different lengths; those of one length are filtered in one batch.
    """
    num_tokens, num_proposals = series.shape[:2]
    checks = np.ones((num_tokens, num_proposals, len(CHECKS)), dtype=bool)
    lengths = np.array([-1 if past is None else len(past) for past in pasts])
    if len(lengths) != num_tokens:
        raise ValueError(f"{len(lengths)} pasts for {num_tokens} tokens")
    for length in np.unique(lengths[lengths >= 0]):
        tokens = np.flatnonzero(lengths == length)
        past = comfort_series(
            np.stack([np.asarray(pasts[int(token)], dtype=np.float64) for token in tokens]), at_centre=True
        )
        padded = np.concatenate(
            [np.broadcast_to(past[:, None], (len(tokens), num_proposals, *past.shape[1:])), series[tokens]],
            axis=2,
        )
        checks[tokens] = comfort_checks(padded, SCORING_INTERVAL_S, V2_2_WINDOWS)
    return checks


def history_comfort(series: FloatArray, pasts: Sequence[FloatArray | None]) -> FloatArray:
    """Return history comfort (B, P), 1.0 or 0.0: whether every check of `history_comfort_checks` passes."""
    return np.asarray(history_comfort_checks(series, pasts).all(axis=-1), dtype=np.float64)
