"""Comfort (C) in {0, 1}, a weighted metric (docs/engine.md, "Comfort filters").

As `pdm_comfort_metrics.py`, quirks included: accelerations are smoothed with the default window 8
(even, so scipy evaluates the fit half a sample late) before the jerk is differentiated with the full
window, the yaw helpers never forward their window (5 applies), every filtered series is rounded to 8
decimals, and bounds are strict. Lateral acceleration sees only the measured value at index 0, since
the simulation writes 0 afterwards.

The devkit filters the proposals it scores at once in one scipy call per series (in evaluation a token's
PDM-Closed reference and submission, in planning PDM-Closed's 15 proposals), and the edge outputs' last
bits depend on that group. The engine filters every series of a batch at once (`savgol.filter_batch`),
which can only differ from the group's call at the edges, by a bounded amount; after rounding to 8
decimals that matters only where an output lies within the bound of a rounding midpoint. The proposals of
such a token are filtered again as a group with scipy's own calls (`savgol.savgol_filter`), so every
rounded value, and so every check, is the devkit's.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import numpy as np
import numpy.typing as npt

from scorer.geometry import BoolArray, FloatArray
from scorer.metrics.savgol import filter_batch, savgol_filter
from scorer.trajectory import StateIndex

DECIMALS = 8
ACCELERATION_WINDOW = 8  # `_extract_ego_acceleration` default
YAW_WINDOW = 5  # `_approximate_derivatives` default
LON_ACCELERATION_BOUNDS = (-4.05, 2.40)
LAT_ACCELERATION_BOUNDS = (-4.89, 4.89)
JERK_BOUNDS = (-8.37, 8.37)
LON_JERK_BOUNDS = (-4.13, 4.13)
YAW_ACCELERATION_BOUNDS = (-1.93, 1.93)
YAW_RATE_BOUNDS = (-0.95, 0.95)
COMFORT_COLUMNS = [StateIndex.ACCELERATION_X, StateIndex.ACCELERATION_Y, StateIndex.HEADING]

# filter(series (..., n), window, poly_order, deriv, delta) -> the filtered series rounded to 8 decimals
Filter = Callable[[FloatArray, int, int, int, float], FloatArray]


def comfort_series(states: FloatArray) -> FloatArray:
    """Return what comfort reads of states (..., n, 11): longitudinal and lateral acceleration, heading."""
    return states[..., COMFORT_COLUMNS]


def _unwrapped(headings: FloatArray) -> FloatArray:
    # nuPlan's `_phase_unwrap`: whole turns removed by rounding the step over 2 pi.
    two_pi = 2.0 * np.pi
    adjustments = np.zeros_like(headings)
    adjustments[..., 1:] = np.cumsum(np.round(np.diff(headings, axis=-1) / two_pi), axis=-1)
    return headings - two_pi * adjustments


def _within(values: FloatArray, bounds: tuple[float, float]) -> npt.NDArray[np.bool_]:
    return np.all((values > bounds[0]) & (values < bounds[1]), axis=-1)


def _filtered_series(series: FloatArray, delta: float, filtered: Filter) -> list[FloatArray]:
    """Return the six filtered series (..., n) the checks bound, from series (..., n, 3), with `filtered`."""
    num_steps = series.shape[-2]
    lon, lat, heading = series[..., 0], series[..., 1], _unwrapped(series[..., 2])
    magnitude = np.hypot(lon, lat)
    return [
        filtered(lon, num_steps, 2, 0, 1.0),
        filtered(lat, num_steps, 2, 0, 1.0),
        filtered(filtered(magnitude, ACCELERATION_WINDOW, 2, 0, 1.0), num_steps, 2, 1, delta),
        filtered(filtered(lon, ACCELERATION_WINDOW, 2, 0, 1.0), num_steps, 2, 1, delta),
        filtered(heading, YAW_WINDOW, 3, 2, delta),
        filtered(heading, YAW_WINDOW, 2, 1, delta),
    ]


BOUNDS = [
    LON_ACCELERATION_BOUNDS,
    LAT_ACCELERATION_BOUNDS,
    JERK_BOUNDS,
    LON_JERK_BOUNDS,
    YAW_ACCELERATION_BOUNDS,
    YAW_RATE_BOUNDS,
]


def _rounded_as_group(
    series: FloatArray, window: int, poly_order: int, deriv: int, delta: float
) -> FloatArray:
    """Filter a token's proposals (P, n) together, as the devkit's call does."""
    window = min(window, series.shape[-1])
    return np.round(savgol_filter(series, window, poly_order, deriv, delta), DECIMALS)


def filtered_series(series: FloatArray, step_s: float) -> tuple[list[FloatArray], npt.NDArray[np.bool_]]:
    """Return the six rounded filtered series (B, P, n) that the comfort checks bound, from each token's
    proposals' `comfort_series` (B, P, n, 3), filtered together as the devkit filters the proposals it scores
    at once; and which tokens (B,) had an output too close to a rounding midpoint and were filtered again as
    a group."""
    num_steps = series.shape[-2]
    delta = float(np.diff(np.arange(num_steps).astype(np.float64) * step_s).mean())
    ambiguous = np.zeros(series.shape[:-2], dtype=bool)

    def rounded_in_batch(
        values: FloatArray, window: int, poly_order: int, deriv: int, step: float
    ) -> FloatArray:
        filtered, error = filter_batch(values, min(window, values.shape[-1]), poly_order, deriv, step)
        scaled = filtered * 10.0**DECIMALS  # np.round's own product: the result is rint of it
        # Outputs within the error bound (and the product's rounding) of a midpoint may round either way.
        tolerance = (error + 2 * np.finfo(np.float64).eps * np.abs(filtered)) * 10.0**DECIMALS
        ambiguous[...] |= (np.abs(scaled - np.floor(scaled) - 0.5) <= tolerance).any(axis=-1)
        return np.round(filtered, DECIMALS)

    outputs = _filtered_series(series, delta, rounded_in_batch)
    regrouped = cast(BoolArray, ambiguous.any(axis=-1))
    for token in np.flatnonzero(regrouped):
        for output, again in zip(
            outputs, _filtered_series(series[token], delta, _rounded_as_group), strict=True
        ):
            output[token] = again
    return outputs, regrouped


def is_comfortable(series: FloatArray, step_s: float) -> npt.NDArray[np.bool_]:
    """Return whether each proposal passes all six comfort checks (B, P), from each token's proposals'
    `comfort_series` (B, P, n, 3)."""
    outputs, _ = filtered_series(series, step_s)
    return np.all([_within(output, bounds) for output, bounds in zip(outputs, BOUNDS, strict=True)], axis=0)
