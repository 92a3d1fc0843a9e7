"""Comfort (C) in {0, 1}, a weighted metric (spec 7.6).

As `pdm_comfort_metrics.py`, quirks included: accelerations are smoothed with the default window 8
(even, so scipy evaluates the fit half a sample late) before the jerk is differentiated with the full
window, the yaw helpers never forward their window (5 applies), every filtered series is rounded to 8
decimals, and bounds are strict. Lateral acceleration sees only the measured value at index 0, since
the simulation writes 0 afterwards.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import numpy.typing as npt
from scipy.signal import savgol_filter

from scorer.geometry import FloatArray
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


@cache
def _savgol_operator(num_steps: int, window: int, poly_order: int, order: int, delta: float) -> FloatArray:
    """Return M (n, n) such that scipy's `savgol_filter(x, mode="interp")` of a series x (n,) is x @ M."""
    window = min(window, num_steps)
    return savgol_filter(
        np.eye(num_steps), window_length=window, polyorder=poly_order, deriv=order, delta=delta, axis=-1
    )


def _filtered(
    series: FloatArray, window: int, poly_order: int = 2, order: int = 0, delta: float = 1.0
) -> FloatArray:
    """Return the series (..., n) filtered along the last axis and rounded to 8 decimals.

    The filter is linear, so it is applied as its matrix, summed in a fixed order per output sample:
    a row's result never depends on the other rows of the batch. It can differ from scipy's own
    arithmetic in the last bits, which the rounding absorbs (see the module notes).
    """
    operator = _savgol_operator(series.shape[-1], window, poly_order, order, delta)
    return np.round((series[..., :, None] * operator).sum(axis=-2), DECIMALS)


def _unwrapped(headings: FloatArray) -> FloatArray:
    # nuPlan's `_phase_unwrap`: whole turns removed by rounding the step over 2 pi.
    two_pi = 2.0 * np.pi
    adjustments = np.zeros_like(headings)
    adjustments[..., 1:] = np.cumsum(np.round(np.diff(headings, axis=-1) / two_pi), axis=-1)
    return headings - two_pi * adjustments


def _within(values: FloatArray, bounds: tuple[float, float]) -> npt.NDArray[np.bool_]:
    return np.all((values > bounds[0]) & (values < bounds[1]), axis=-1)


def is_comfortable(states: FloatArray, step_s: float) -> npt.NDArray[np.bool_]:
    """Return whether each proposal's states (P, T, 11) pass all six comfort checks (P,)."""
    num_steps = states.shape[1]
    delta = float(np.diff(np.arange(num_steps).astype(np.float64) * step_s).mean())
    lon = states[..., StateIndex.ACCELERATION_X]
    lat = states[..., StateIndex.ACCELERATION_Y]
    magnitude = np.hypot(lon, lat)
    heading = _unwrapped(states[..., StateIndex.HEADING])
    checks = [
        _within(_filtered(lon, num_steps), LON_ACCELERATION_BOUNDS),
        _within(_filtered(lat, num_steps), LAT_ACCELERATION_BOUNDS),
        _within(_filtered(_filtered(magnitude, ACCELERATION_WINDOW), num_steps, 2, 1, delta), JERK_BOUNDS),
        _within(_filtered(_filtered(lon, ACCELERATION_WINDOW), num_steps, 2, 1, delta), LON_JERK_BOUNDS),
        _within(_filtered(heading, YAW_WINDOW, 3, 2, delta), YAW_ACCELERATION_BOUNDS),
        _within(_filtered(heading, YAW_WINDOW, 2, 1, delta), YAW_RATE_BOUNDS),
    ]
    return np.all(checks, axis=0)
