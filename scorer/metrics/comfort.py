"""Comfort (C) in {0, 1}, a weighted metric, and the comfort functions of v2.2's history comfort
(docs/engine.md, "Comfort filters").

As `pdm_comfort_metrics.py`, quirks included: accelerations are smoothed with the default window 8
(even, so scipy evaluates the fit half a sample late) before the jerk is differentiated, the yaw helpers
never forward their window (5 applies), every filtered series is rounded to 8 decimals, and bounds are
strict. Of the simulated states, lateral acceleration sees only the measured value at index 0: the
simulation writes 0 afterwards. v2.2 changed two things: v1.x passes the whole series as the window of
both accelerations and of both jerk derivatives, v2.2 forwards none, so 8 and 15 apply (`Windows`); and
v2.2 reads the longitudinal acceleration at the vehicle centre while the jerk still differentiates the
rear axle's magnitude (`comfort_series`).

The devkit filters the proposals it scores at once in one scipy call per series (in evaluation a token's
PDM-Closed reference and submission, in planning PDM-Closed's 15 proposals), and the edge outputs' last
bits depend on that group. The engine filters every series of a batch at once (`savgol.filter_batch`),
which can only differ from the group's call at the edges, by a bounded amount; after rounding to 8
decimals that matters only where an output lies within the bound of a rounding midpoint. The proposals of
such a token are filtered again as a group with scipy's own calls (`savgol.savgol_filter`), so every
rounded value, and so every check, is the devkit's. `filtered_as_devkit` does this for any chain of
filters: the two-frame extended comfort's too.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from enum import IntEnum
from functools import partial
from typing import NamedTuple, cast

import numpy as np
import numpy.typing as npt

from scorer.geometry import REAR_AXLE_TO_CENTER, BoolArray, FloatArray
from scorer.metrics.savgol import filter_batch, savgol_filter
from scorer.trajectory import StateIndex

DECIMALS = 8
ACCELERATION_WINDOW = 8  # `_extract_ego_acceleration` default
JERK_WINDOW = 15  # `_extract_ego_jerk` default
YAW_WINDOW = 5  # `_approximate_derivatives` default
LON_ACCELERATION_BOUNDS = (-4.05, 2.40)
LAT_ACCELERATION_BOUNDS = (-4.89, 4.89)
JERK_BOUNDS = (-8.37, 8.37)
LON_JERK_BOUNDS = (-4.13, 4.13)
YAW_ACCELERATION_BOUNDS = (-1.93, 1.93)
YAW_RATE_BOUNDS = (-0.95, 0.95)
# The six checks in the devkit's order (`ego_is_comfortable`), with their bounds.
CHECKS = ("lon_acceleration", "lat_acceleration", "jerk", "lon_jerk", "yaw_accel", "yaw_rate")
BOUNDS = [
    LON_ACCELERATION_BOUNDS,
    LAT_ACCELERATION_BOUNDS,
    JERK_BOUNDS,
    LON_JERK_BOUNDS,
    YAW_ACCELERATION_BOUNDS,
    YAW_RATE_BOUNDS,
]


class SeriesIndex(IntEnum):
    """Columns of `comfort_series`: what the comfort filters read of a state."""

    LON_ACCELERATION = 0
    LAT_ACCELERATION = 1
    HEADING = 2
    ACCELERATION_MAGNITUDE = 3  # at the rear axle in every version


class Windows(NamedTuple):
    """Savitzky-Golay windows of the two acceleration checks and of the two jerk derivatives; the devkit
    clips each to the series length (`min(window_length, n_time)`)."""

    acceleration: int
    jerk: int


# v1.x passes `window_length=n_time`: after the clipping, the same as any longer window.
WHOLE_SERIES = sys.maxsize
V1_WINDOWS = Windows(acceleration=WHOLE_SERIES, jerk=WHOLE_SERIES)
V2_2_WINDOWS = Windows(acceleration=ACCELERATION_WINDOW, jerk=JERK_WINDOW)

# filter(series (..., n), window, poly_order, deriv, delta) -> the filtered series rounded to 8 decimals
Filter = Callable[[FloatArray, int, int, int, float], FloatArray]
# features(comfort series (..., n, 4), delta, filter) -> the rounded filtered series (..., n) a metric reads
Features = Callable[[FloatArray, float, Filter], list[FloatArray]]


def comfort_series(states: FloatArray, at_centre: bool = False) -> FloatArray:
    """Return what comfort reads of states (..., n, 11), columns `SeriesIndex`; with `at_centre` (v2.2) the
    longitudinal acceleration at the vehicle centre.

    The centre is PDM's `state_array_to_center_state_array`, nuPlan's rigid-body shift by (d, 0):
    ax + d·ω² + d·α, summed in that order; the lateral acceleration gains 0·ω² + 0·α, nothing.
    """
    lon = states[..., StateIndex.ACCELERATION_X]
    lat = states[..., StateIndex.ACCELERATION_Y]
    magnitude = np.hypot(lon, lat)
    if at_centre:
        angular_velocity = states[..., StateIndex.ANGULAR_VELOCITY]
        angular_acceleration = states[..., StateIndex.ANGULAR_ACCELERATION]
        lon = lon + REAR_AXLE_TO_CENTER * angular_velocity**2 + REAR_AXLE_TO_CENTER * angular_acceleration
    return np.stack([lon, lat, states[..., StateIndex.HEADING], magnitude], axis=-1)


def unwrapped(headings: FloatArray) -> FloatArray:
    """Return headings (..., n) with whole turns removed by rounding each step over 2 pi (`_phase_unwrap`)."""
    two_pi = 2.0 * np.pi
    adjustments = np.zeros_like(headings)
    adjustments[..., 1:] = np.cumsum(np.round(np.diff(headings, axis=-1) / two_pi), axis=-1)
    return headings - two_pi * adjustments


def _within(values: FloatArray, bounds: tuple[float, float]) -> npt.NDArray[np.bool_]:
    return np.all((values > bounds[0]) & (values < bounds[1]), axis=-1)


def _filtered_series(
    series: FloatArray, delta: float, filtered: Filter, windows: Windows = V1_WINDOWS
) -> list[FloatArray]:
    """Return the six filtered series (..., n) the checks bound, from series (..., n, 4), with `filtered`."""
    lon = series[..., SeriesIndex.LON_ACCELERATION]
    heading = unwrapped(series[..., SeriesIndex.HEADING])
    magnitude = series[..., SeriesIndex.ACCELERATION_MAGNITUDE]
    return [
        filtered(lon, windows.acceleration, 2, 0, 1.0),
        filtered(series[..., SeriesIndex.LAT_ACCELERATION], windows.acceleration, 2, 0, 1.0),
        filtered(filtered(magnitude, ACCELERATION_WINDOW, 2, 0, 1.0), windows.jerk, 2, 1, delta),
        filtered(filtered(lon, ACCELERATION_WINDOW, 2, 0, 1.0), windows.jerk, 2, 1, delta),
        filtered(heading, YAW_WINDOW, 3, 2, delta),
        filtered(heading, YAW_WINDOW, 2, 1, delta),
    ]


def _rounded_as_group(
    series: FloatArray, window: int, poly_order: int, deriv: int, delta: float
) -> FloatArray:
    """Filter a token's proposals (P, n) together, as the devkit's call does."""
    window = min(window, series.shape[-1])
    return np.round(savgol_filter(series, window, poly_order, deriv, delta), DECIMALS)


def filtered_as_devkit(
    series: FloatArray, step_s: float, features: Features
) -> tuple[list[FloatArray], npt.NDArray[np.bool_]]:
    """Return the rounded filtered series (B, G, n) `features` makes of B groups' comfort series
    (B, G, n, 4), each group's series filtered together as one devkit call filters them; and which groups
    (B,) had an output too close to a rounding midpoint and were filtered again as a group.

    The time steps are the devkit's `arange(n) * step_s`, their mean difference the derivatives' delta.
    """
    num_steps = series.shape[-2]
    delta = float(np.diff(np.arange(num_steps).astype(np.float64) * step_s).mean())
    ambiguous = np.zeros(series.shape[:-2], dtype=bool)

    def rounded_in_batch(
        values: FloatArray, window: int, poly_order: int, deriv: int, step: float
    ) -> FloatArray:
        filtered, error = filter_batch(values, min(window, values.shape[-1]), poly_order, deriv, step)
        scaled = filtered * 10.0**DECIMALS  # np.round's own product: the result is rint of it
        # Outputs within the error bound (and the product's rounding) of a midpoint may round either way. An
        # output without error (the convolution's) holds the group call's very bits, so it rounds as the
        # devkit's does however near a midpoint it lies.
        tolerance = (error + 2 * np.finfo(np.float64).eps * np.abs(filtered)) * 10.0**DECIMALS
        near_midpoint = np.abs(scaled - np.floor(scaled) - 0.5) <= tolerance
        ambiguous[...] |= (near_midpoint & (error > 0)).any(axis=-1)
        return np.round(filtered, DECIMALS)

    outputs = features(series, delta, rounded_in_batch)
    regrouped = cast(BoolArray, ambiguous.any(axis=-1))
    for group in np.flatnonzero(regrouped):
        for output, again in zip(outputs, features(series[group], delta, _rounded_as_group), strict=True):
            output[group] = again
    return outputs, regrouped


def filtered_series(
    series: FloatArray, step_s: float, windows: Windows = V1_WINDOWS
) -> tuple[list[FloatArray], npt.NDArray[np.bool_]]:
    """Return the six rounded filtered series (B, P, n) that the comfort checks bound, from each token's
    proposals' `comfort_series` (B, P, n, 4), filtered together as the devkit filters the proposals it scores
    at once; and which tokens (B,) were filtered again as a group (`filtered_as_devkit`)."""
    return filtered_as_devkit(series, step_s, partial(_filtered_series, windows=windows))


def comfort_checks(series: FloatArray, step_s: float, windows: Windows = V1_WINDOWS) -> BoolArray:
    """Return whether each proposal passes each of the six comfort checks (B, P, 6), in `CHECKS` order, from
    each token's proposals' `comfort_series` (B, P, n, 4)."""
    outputs, _ = filtered_series(series, step_s, windows)
    return np.stack(
        [_within(output, bounds) for output, bounds in zip(outputs, BOUNDS, strict=True)], axis=-1
    )


def is_comfortable(series: FloatArray, step_s: float) -> BoolArray:
    """Return whether each proposal passes all six comfort checks of v1.x (B, P), from each token's proposals'
    `comfort_series` (B, P, n, 4)."""
    return cast(BoolArray, comfort_checks(series, step_s).all(axis=-1))
