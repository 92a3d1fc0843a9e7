"""Vectorised forms of the devkit's numerics give its exact floats: DDC window sums and comfort filters."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import savgol_filter

from scorer.geometry import FloatArray
from scorer.metrics.comfort import (
    ACCELERATION_WINDOW,
    Filter,
    comfort_series,
    filtered_as_devkit,
    filtered_series,
    is_comfortable,
)
from scorer.metrics.driving_direction import _time_windows
from scorer.trajectory import StateIndex

MIDPOINT = Path(__file__).parent / "fixtures" / "comfort-midpoint.json"


@pytest.mark.parametrize("horizon", [3, 7, 10, 12, 20])
def test_time_windows_are_numpy_sums_of_each_slice(horizon: int) -> None:
    rng = np.random.default_rng(horizon)
    steps = (
        rng.random((4, 300, 41))
        * (rng.random((4, 300, 41)) > 0.4)
        * rng.choice([1e-3, 1.0, 3.0], (4, 300, 1))
    )
    literal = np.stack([steps[..., max(0, k - horizon) : k + 1].sum(axis=-1) for k in range(41)], axis=-1)
    assert np.array_equal(_time_windows(steps, horizon), literal)


def _devkit_comfort(states: np.ndarray) -> np.ndarray:
    """`ego_is_comfortable` transcribed with scipy's own filter calls (window quirks, rounding, bounds)."""
    n = states.shape[1]
    delta = np.diff(np.arange(n).astype(np.float64) * 0.1).mean()
    ax, ay, heading = (
        states[..., StateIndex.ACCELERATION_X],
        states[..., StateIndex.ACCELERATION_Y],
        states[..., 2],
    )
    two_pi = 2.0 * np.pi
    adjustments = np.zeros_like(heading)
    adjustments[..., 1:] = np.cumsum(np.round(np.diff(heading, axis=-1) / two_pi), axis=-1)
    unwrapped = heading - two_pi * adjustments

    def smooth(series: np.ndarray, window: int) -> np.ndarray:
        return np.round(savgol_filter(series, polyorder=2, window_length=window, axis=-1), 8)

    def derive(series: np.ndarray, window: int, order: int, poly: int) -> np.ndarray:
        return np.round(
            savgol_filter(series, polyorder=poly, window_length=window, deriv=order, delta=delta, axis=-1), 8
        )

    def within(values: np.ndarray, low: float, high: float) -> np.ndarray:
        return np.all((values > low) & (values < high), axis=-1)

    return (
        within(smooth(ax, n), -4.05, 2.40)
        & within(smooth(ay, n), -4.89, 4.89)
        & within(derive(smooth(np.hypot(ax, ay), 8), n, 1, 2), -8.37, 8.37)
        & within(derive(smooth(ax, 8), n, 1, 2), -4.13, 4.13)
        & within(derive(unwrapped, 5, 2, 3), -1.93, 1.93)
        & within(derive(unwrapped, 5, 1, 2), -0.95, 0.95)
    )


def test_comfort_filters_a_tokens_proposals_as_the_devkits_call_does() -> None:
    # Random drives scaled so that about half of them break some bound, scored in pairs as in evaluation.
    rng = np.random.default_rng(5)
    states = np.zeros((600, 41, 11))
    scale = rng.choice([0.3, 1.0, 2.0, 4.0], (600, 1))
    states[..., StateIndex.ACCELERATION_X] = np.cumsum(rng.normal(0, 0.15, (600, 41)), axis=1) * scale
    states[:, 0, StateIndex.ACCELERATION_Y] = rng.normal(0, 8.0, 600)
    headings = np.cumsum(rng.normal(0, 0.005, (600, 41)), axis=1) * scale + rng.uniform(-4, 4, (600, 1))
    states[..., StateIndex.HEADING] = (headings + np.pi) % (2 * np.pi) - np.pi
    pairs = states.reshape(300, 2, 41, 11)
    expected = np.array([_devkit_comfort(pair) for pair in pairs])
    assert 0.2 < expected.mean() < 0.8
    assert np.array_equal(is_comfortable(comfort_series(pairs), 0.1), expected)


def test_an_output_on_a_rounding_midpoint_rounds_as_the_devkits_call_on_the_pair() -> None:
    lon = np.array(json.loads(MIDPOINT.read_text())["lon_acceleration"])
    devkit = savgol_filter(lon, window_length=41, polyorder=2, axis=-1)
    scaled = devkit[1, 3] * 1e8
    assert abs(scaled - np.floor(scaled) - 0.5) < 1e-6  # the fixture sits on a midpoint
    states = np.zeros((1, 2, 41, 11))
    states[0, :, :, StateIndex.ACCELERATION_X] = lon
    outputs, regrouped = filtered_series(comfort_series(states), 0.1)
    assert regrouped.tolist() == [True]
    np.testing.assert_array_equal(outputs[0][0], np.round(devkit, 8))


def test_an_output_of_the_convolution_near_a_midpoint_is_not_filtered_again() -> None:
    # Output 20 of the window-8 smoothing is set by the convolution (no error bound) and lies within the
    # rounding of np.round's product of a midpoint; the edge outputs lie far from any.
    lon = 0.1 + 0.01 * np.sin(np.arange(41) * 0.7)
    lon[20] = float.fromhex("0x1.c22cdb70c4d5ep-4")
    devkit = savgol_filter(lon[None], window_length=ACCELERATION_WINDOW, polyorder=2, axis=-1)
    scaled = devkit[0, 20] * 1e8
    assert abs(scaled - np.floor(scaled) - 0.5) < 1e-8  # the fixture sits on a midpoint
    series = np.zeros((1, 1, 41, 4))
    series[..., 0] = lon

    def smoothed(values: FloatArray, delta: float, filtered: Filter) -> list[FloatArray]:
        return [filtered(values[..., 0], ACCELERATION_WINDOW, 2, 0, 1.0)]

    outputs, regrouped = filtered_as_devkit(series, 0.1, smoothed)
    assert regrouped.tolist() == [False]
    np.testing.assert_array_equal(outputs[0][0], np.round(devkit, 8))
