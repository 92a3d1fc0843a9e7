"""Two-frame extended comfort (EC) against the official v2.2 results on all 208 pairs (16 adjacent probe
pairs x 13 families), and against the devkit's per-frame scipy calls on random pairs of every overlap.

As for history comfort, EC runs on the reference's own simulated agent states of both frames.
"""

from __future__ import annotations

import numpy as np
import pytest
from epdms_reference import rows, scene
from scipy.signal import savgol_filter

from scorer.metrics.two_frame_comfort import FEATURES, overlap_steps, two_frame_extended_comfort
from scorer.trajectory import StateIndex


def _devkit_rms(current: np.ndarray, previous: np.ndarray, steps: int) -> list[float]:
    """`SceneAggregator._compute_two_frame_comfort` transcribed with scipy's calls: each frame (41, 11) a batch
    of one, four features each, the RMS of their differences."""
    states_1, states_2 = current[:-steps][None], previous[steps:][None]
    time_point_s = np.arange(states_1.shape[1]) * 0.1
    dx = np.diff(time_point_s, axis=-1).mean()

    def features(states: np.ndarray) -> list[np.ndarray]:
        n = states.shape[1]
        magnitude = np.hypot(states[..., StateIndex.ACCELERATION_X], states[..., StateIndex.ACCELERATION_Y])
        acceleration = np.round(savgol_filter(magnitude, polyorder=2, window_length=min(8, n), axis=-1), 8)
        heading = states[..., StateIndex.HEADING]
        adjustments = np.zeros_like(heading)
        adjustments[..., 1:] = np.cumsum(np.round(np.diff(heading, axis=-1) / (2.0 * np.pi)), axis=-1)
        heading = heading - 2.0 * np.pi * adjustments

        def derivative(series: np.ndarray, window: int, deriv: int) -> np.ndarray:
            window = min(window, len(time_point_s))
            filtered = savgol_filter(
                series, polyorder=2, window_length=window, deriv=deriv, delta=dx, axis=-1
            )
            return np.round(filtered, 8)

        return [
            acceleration,
            derivative(acceleration, min(15, n), 1),
            derivative(heading, 5, 1),
            derivative(heading, 5, 2),
        ]

    return [
        float(np.sqrt(np.mean((one - two) ** 2, axis=1))[0])
        for one, two in zip(features(states_1), features(states_2), strict=True)
    ]


def test_ec_of_every_official_pair() -> None:
    by_token = {(row.family, row.scene_path.parent, row.token): row for row in rows()}
    pairs = [
        (row, by_token[(row.family, row.scene_path.parent, row.line["adjacent_previous_token"])])
        for row in rows()
        if row.line["adjacent_previous_token"]
    ]
    steps = []
    for current, previous in pairs:
        current_us = scene(current.scene_path).current_frame.timestamp_us
        previous_us = scene(previous.scene_path).current_frame.timestamp_us
        assert (current.line["start_time"], previous.line["start_time"]) == (
            current_us * 1e-6,
            previous_us * 1e-6,
        )
        steps.append(overlap_steps(current_us, previous_us))
    assert steps == [current.diagnostics["ec_k"] for current, _ in pairs]

    ec = two_frame_extended_comfort(
        np.array([current.diagnostics["agent_states"] for current, _ in pairs]),
        np.array([previous.diagnostics["agent_states"] for _, previous in pairs]),
        steps,
    )

    official = np.array([current.line["two_frame_extended_comfort"] for current, _ in pairs])
    assert len(pairs) == 208 and 0.1 < official.mean() < 0.9
    np.testing.assert_array_equal(ec.value, official)
    expected_rms = np.array(
        [[current.diagnostics["ec_rms"][name] for name in FEATURES] for current, _ in pairs]
    )
    np.testing.assert_allclose(ec.rms, expected_rms, rtol=0, atol=1e-9)
    # Rows without a partner have no EC.
    assert all(
        row.line["two_frame_extended_comfort"] is None
        for row in rows()
        if not row.line["adjacent_previous_token"]
    )


def _random_pairs(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return simulated-like previous and current frames (count, 41, 11) that overlap `steps` (count,) apart,
    the current one a perturbed continuation of the previous, about half within every threshold."""
    steps = rng.integers(1, 6, count)
    time_s = np.arange(41 + 5) * 0.1
    acceleration = rng.normal(0, 1.0, (count, 1)) + np.cumsum(rng.normal(0, 0.2, (count, 46)), axis=1)
    heading = rng.uniform(-np.pi, np.pi, (count, 1)) + np.cumsum(rng.normal(0, 0.01, (count, 46)), axis=1)
    scale = rng.choice([0.01, 0.1, 0.5], (count, 1))
    previous, current = np.zeros((count, 41, 11)), np.zeros((count, 41, 11))
    for pair, step in enumerate(steps):
        previous[pair, :, StateIndex.ACCELERATION_X] = acceleration[pair, :41]
        previous[pair, :, StateIndex.HEADING] = heading[pair, :41]
        current[pair, :, StateIndex.ACCELERATION_X] = acceleration[pair, step : step + 41] + scale[
            pair
        ] * np.sin(time_s[:41] * rng.uniform(1, 6))
        current[pair, :, StateIndex.HEADING] = heading[pair, step : step + 41] + 0.2 * scale[pair] * np.sin(
            time_s[:41] * rng.uniform(1, 6)
        )
    for frames in (previous, current):
        frames[:, 0, StateIndex.ACCELERATION_Y] = rng.normal(0, 1.0, count)
        frames[..., StateIndex.HEADING] = (frames[..., StateIndex.HEADING] + np.pi) % (2 * np.pi) - np.pi
    return current, previous, steps


def test_ec_is_the_devkits_per_frame_calls_at_every_overlap() -> None:
    current, previous, steps = _random_pairs(np.random.default_rng(11), 400)

    ec = two_frame_extended_comfort(current, previous, steps)

    expected = np.array([_devkit_rms(*pair) for pair in zip(current, previous, steps, strict=True)])
    np.testing.assert_array_equal(ec.rms, expected)
    thresholds = np.array([0.7, 0.5, 0.1, 0.1])
    np.testing.assert_array_equal(ec.value, (expected <= thresholds).all(axis=1).astype(float))
    assert 0.2 < ec.value.mean() < 0.8 and set(steps.tolist()) == {1, 2, 3, 4, 5}


def test_overlap_steps_and_the_devkits_failures() -> None:
    start_us = 1_620_016_664_250_000
    assert overlap_steps(start_us, start_us - 500_000) == 5
    assert overlap_steps(start_us, start_us - 260_000) == 3
    assert overlap_steps(start_us, start_us - 149_000) == 1
    # A nominal 0.55 s in float seconds falls either side of the assertion.
    assert overlap_steps(1_620_016_664_300_000, 1_620_016_663_750_000) == 5  # 0.5499999523162842 s
    for current_us, previous_us in (
        (1_620_016_664_250_000, 1_620_016_663_700_000),  # 0.5500001907348633 s
        (1_050_000, 500_000),  # 0.55 s
        (1_000_000, 1_000_000),
        (500_000, 1_000_000),
        (1_600_000, 1_000_000),
    ):
        with pytest.raises(ValueError, match="asserts"):
            overlap_steps(current_us, previous_us)
    with pytest.raises(ValueError, match="0 steps"):
        overlap_steps(start_us, start_us - 40_000)
