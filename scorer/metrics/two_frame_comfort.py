"""Two-frame extended comfort (EC) in {0, 1}, a weighted metric of v2.2 joined per split: how much a
token's simulated plan changes the comfort series of the plan made at the adjacent previous frame of its log
(docs/engine.md, "Comfort filters").

As `SceneAggregator._compute_two_frame_comfort` and `ego_is_two_frame_extended_comfort`: the frames are
k = round(Δt / 0.1) steps apart, Δt the difference of the two start times in float seconds
(`TimePoint.time_s`, time_us * 1e-6), and the overlap is current[:-k] against previous[k:], 41 - k
simulated states each on the grid arange(41 - k) * 0.1. Of each, four series: the rear axle's acceleration
magnitude (window 8, poly 2), its jerk (the derivative of that rounded acceleration, window 15, poly 2),
yaw rate and yaw acceleration (first and second derivative of the unwrapped heading, window 5, both poly
2: `extract_features` forwards no poly order, where history comfort's yaw acceleration uses 3); each
rounded to 8 decimals. EC = 1 iff the RMS over time of each series' difference is at most 0.7, 0.5, 0.1,
0.1 (inclusive, unlike the comfort bounds).

The aggregator filters each frame on its own, a batch of one per scipy call, so each frame's series are
one filter group (`comfort.filtered_as_devkit`), and the RMS is numpy's mean over the time axis of each
pair, as the devkit's (1, n) arrays give it.
"""

from __future__ import annotations

from typing import NamedTuple, cast

import numpy as np
import numpy.typing as npt

from scorer.geometry import FloatArray
from scorer.metrics.comfort import (
    ACCELERATION_WINDOW,
    JERK_WINDOW,
    YAW_WINDOW,
    Filter,
    SeriesIndex,
    comfort_series,
    filtered_as_devkit,
    unwrapped,
)
from scorer.trajectory import SCORING_INTERVAL_S

FEATURES = ("acceleration", "jerk", "yaw_rate", "yaw_accel")
RMS_THRESHOLDS = np.array([0.7, 0.5, 0.1, 0.1])  # `pdm_comfort_metrics.py` extended comfort thresholds
MAX_INTERVAL_S = 0.55  # the aggregator asserts 0 < Δt < 0.55
ADJACENT_GAP_S = 0.55  # `infer_start_adjacent_mapping`'s time_gap_threshold: the frames EC pairs


class TwoFrameComfort(NamedTuple):
    """EC of N pairs: `value` (N,) 1.0 or 0.0 and `rms` (N, 4), the RMS differences in `FEATURES` order."""

    value: FloatArray
    rms: FloatArray


def overlap_steps(current_start_us: int, previous_start_us: int) -> int:
    """Return k, the steps of 0.1 s between two frames' starts: Python's round of Δt / 0.1 in float seconds.

    Raises ValueError where the devkit's aggregator fails: Δt not in (0, 0.55) s (its assertion), or k = 0
    (the overlaps current[:-0] and previous[0:] differ in length).
    """
    interval_s = current_start_us * 1e-6 - previous_start_us * 1e-6
    if not 0 < interval_s < MAX_INTERVAL_S:
        raise ValueError(f"frames {interval_s} s apart: the devkit asserts 0 < Δt < {MAX_INTERVAL_S}")
    steps = round(interval_s / SCORING_INTERVAL_S)
    if steps == 0:
        raise ValueError(f"frames {interval_s} s apart overlap on 0 steps: the devkit's shapes differ")
    return steps


def _features(series: FloatArray, delta: float, filtered: Filter) -> list[FloatArray]:
    """Return `extract_features`' four rounded series (..., n) of comfort series (..., n, 4)."""
    acceleration = filtered(series[..., SeriesIndex.ACCELERATION_MAGNITUDE], ACCELERATION_WINDOW, 2, 0, 1.0)
    heading = unwrapped(series[..., SeriesIndex.HEADING])
    return [
        acceleration,
        filtered(acceleration, JERK_WINDOW, 2, 1, delta),
        filtered(heading, YAW_WINDOW, 2, 1, delta),
        filtered(heading, YAW_WINDOW, 2, 2, delta),
    ]


def two_frame_extended_comfort(
    current: FloatArray, previous: FloatArray, steps: npt.ArrayLike
) -> TwoFrameComfort:
    """Return EC of N pairs of simulated agent states, current (N, 41, 11) against the adjacent previous
    frame's (N, 41, 11), `steps` (N,) apart (`overlap_steps`)."""
    current = np.asarray(current, dtype=np.float64)
    previous = np.asarray(previous, dtype=np.float64)
    shifts = np.asarray(steps, dtype=np.int64)
    rms = np.zeros((len(shifts), len(FEATURES)))
    for step in np.unique(shifts):
        pairs = np.flatnonzero(shifts == step)
        frames = np.concatenate([current[pairs, :-step], previous[pairs, step:]])
        # Each frame a group of one: (2 * pairs, 1, 41 - k, 4).
        outputs, _ = filtered_as_devkit(comfort_series(frames)[:, None], SCORING_INTERVAL_S, _features)
        for feature, output in enumerate(outputs):
            difference = output[: len(pairs), 0] - output[len(pairs) :, 0]
            rms[pairs, feature] = np.sqrt(np.mean(difference**2, axis=1))
    value = cast(FloatArray, (rms <= RMS_THRESHOLDS).all(axis=-1).astype(np.float64))
    return TwoFrameComfort(value=value, rms=rms)
