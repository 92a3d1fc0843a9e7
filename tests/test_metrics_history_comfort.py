"""History comfort (HC) against the official v2.2 results: the past states bit for bit, the six checks and HC
on all 1,846 tokens (520 public, 1,326 probe), and every rounded series against scipy's own calls.

The comfort functions run on the reference's own simulated agent states (`diagnostics.agent_states`, which
our simulation gives bit for bit: test_host_independence). PDM-Closed's states, the other member of the
devkit's filter group, are our simulation of the cached trajectory.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest
from epdms_reference import Row, rows, scene
from scipy.interpolate import interp1d
from scipy.signal import savgol_filter

from scorer.geometry import principal_value, rear_axle_round_trip
from scorer.metrics.comfort import CHECKS, V2_2_WINDOWS, comfort_series, filtered_series
from scorer.metrics.history_comfort import history_comfort, history_comfort_checks, past_states
from scorer.scene import Scene
from scorer.simulation import simulate
from scorer.trajectory import SCORING_INTERVAL_S, StateIndex, initial_state, pdm_references

# Families whose rounded series are compared with scipy's calls one token at a time (the slow part).
TRANSCRIBED_FAMILIES = ("human", "swerve_left_fast", "zigzag")


def _devkit_series(padded: np.ndarray) -> list[np.ndarray]:
    """v2.2's `ego_is_comfortable` on one call's states (P, n, 11), transcribed with scipy's calls: the six
    rounded series the checks bound (centre accelerations by `get_acceleration_shifted` with (d, 0))."""
    n = padded.shape[1]
    delta = np.diff(np.arange(0, n).astype(np.float64) * 0.1).mean()
    d = (4.049 + 1.127) / 2.0 - 1.127  # pacifica half_length - rear_length
    ax, ay = padded[..., StateIndex.ACCELERATION_X], padded[..., StateIndex.ACCELERATION_Y]
    omega, alpha = padded[..., StateIndex.ANGULAR_VELOCITY], padded[..., StateIndex.ANGULAR_ACCELERATION]
    centre_ax, centre_ay = ax + d * omega**2 + d * alpha, ay + 0.0 * omega**2 + 0.0 * alpha
    heading = padded[..., StateIndex.HEADING]
    adjustments = np.zeros_like(heading)
    adjustments[..., 1:] = np.cumsum(np.round(np.diff(heading, axis=-1) / (2.0 * np.pi)), axis=-1)
    heading = heading - 2.0 * np.pi * adjustments

    def filtered(
        series: np.ndarray, window: int, poly: int = 2, deriv: int = 0, dx: float = 1.0
    ) -> np.ndarray:
        window = min(window, n)
        return np.round(
            savgol_filter(series, polyorder=poly, window_length=window, deriv=deriv, delta=dx, axis=-1), 8
        )

    return [
        filtered(centre_ax, 8),
        filtered(centre_ay, 8),
        filtered(filtered(np.hypot(ax, ay), 8), 15, 2, 1, delta),
        filtered(filtered(centre_ax, 8), 15, 2, 1, delta),
        filtered(heading, 5, 3, 2, delta),
        filtered(heading, 5, 2, 1, delta),
    ]


def _devkit_checks(padded: np.ndarray) -> np.ndarray:
    bounds = [(-4.05, 2.40), (-4.89, 4.89), (-8.37, 8.37), (-4.13, 4.13), (-1.93, 1.93), (-0.95, 0.95)]
    return np.stack(
        [
            np.all((series > low) & (series < high), axis=-1)
            for series, (low, high) in zip(_devkit_series(padded), bounds, strict=True)
        ],
        axis=-1,
    )


@cache
def _groups() -> tuple[np.ndarray, np.ndarray]:
    """Return each official token's filter group (N, 2, 41, 11), [our PDM-Closed, the reference's agent],
    and the reference's past states (N, 14, 11)."""
    frames = [scene(row.scene_path).current_frame for row in rows()]
    trajectories = np.array([row.diagnostics["pdm_closed_trajectory"] for row in rows()])[..., 1:4]
    pdm = simulate(
        pdm_references(np.array([frame.timestamp_us for frame in frames]), trajectories),
        np.array([initial_state(frame.ego) for frame in frames]),
    )
    agents = np.array([row.diagnostics["agent_states"] for row in rows()])
    pasts = np.array([row.diagnostics["past_states"] for row in rows()])
    return np.stack([pdm, agents], axis=1), pasts


def _padded(states: np.ndarray, past: np.ndarray) -> np.ndarray:
    return np.concatenate([np.broadcast_to(past, (len(states), *past.shape)), states], axis=1)


def test_the_past_states_are_the_official_bit_for_bit() -> None:
    by_scene: dict[Path, list[Row]] = {}
    for row in rows():
        by_scene.setdefault(row.scene_path, []).append(row)
    assert len(by_scene) == 142
    for path, scene_rows in by_scene.items():
        ours = past_states(scene(path))
        assert ours.shape == (14, 11)
        for row in scene_rows:
            np.testing.assert_array_equal(ours, np.array(row.diagnostics["past_states"]), err_msg=row.token)


def test_the_six_checks_and_history_comfort_are_the_official_on_every_token() -> None:
    groups, pasts = _groups()
    checks = history_comfort_checks(comfort_series(groups, at_centre=True), list(pasts))
    expected = np.array([[row.diagnostics["comfort_checks"][check] for check in CHECKS] for row in rows()])
    official = np.array([row.line["history_comfort"] for row in rows()])
    assert len(rows()) == 1846 and 0.5 < official.mean() < 0.8 and not expected.all()
    differing = [
        row.token
        for row, ours, theirs in zip(rows(), checks[:, 1], expected, strict=True)
        if (ours != theirs).any()
    ]
    assert differing == []
    np.testing.assert_array_equal(
        history_comfort(comfort_series(groups, at_centre=True), list(pasts))[:, 1], official
    )


def test_every_rounded_series_is_the_devkits_call_on_the_token_pair() -> None:
    groups, pasts = _groups()
    chosen = [index for index, row in enumerate(rows()) if row.family in TRANSCRIBED_FAMILIES]
    padded = np.stack([_padded(groups[index], pasts[index]) for index in chosen])
    outputs, regrouped = filtered_series(
        comfort_series(padded, at_centre=True), SCORING_INTERVAL_S, V2_2_WINDOWS
    )
    assert regrouped.any()  # some pairs need the group's own call
    for position, index in enumerate(chosen):
        for ours, devkit in zip(outputs, _devkit_series(padded[position]), strict=True):
            np.testing.assert_array_equal(ours[position], devkit, err_msg=rows()[index].token)


def _jittered(source: Scene, offsets_us: tuple[int, int, int]) -> Scene:
    """Return `source` with its three past frames moved by `offsets_us` (later is positive)."""
    first = source.current_index - 3
    frames = list(source.frames)
    for frame_index, offset in zip(range(first, source.current_index), offsets_us, strict=True):
        frames[frame_index] = frames[frame_index]._replace(
            timestamp_us=frames[frame_index].timestamp_us + offset
        )
    return source._replace(frames=tuple(frames))


def test_jittered_past_frames_are_sampled_as_the_interpolated_trajectory() -> None:
    row = next(row for row in rows() if row.family == "zigzag" and row.line["history_comfort"] == 1.0)
    source = scene(row.scene_path)
    jittered = _jittered(source, (-60_000, 30_000, -20_000))
    frames = jittered.frames[jittered.current_index - 3 : jittered.current_index + 1]
    knot_times = np.array([frame.timestamp_us for frame in frames], dtype=np.float64)
    knots = np.array([initial_state(frame.ego) for frame in frames])
    times = np.arange(frames[0].timestamp_us, frames[-1].timestamp_us, 100_000, dtype=np.int64)[:-1]

    past = past_states(jittered)

    assert len(times) == 15 and past.shape == (15, 11)  # 1.56 s of past: one state more
    linear = [
        StateIndex.VELOCITY_X,
        StateIndex.VELOCITY_Y,
        StateIndex.ACCELERATION_X,
        StateIndex.ACCELERATION_Y,
    ]
    np.testing.assert_array_equal(past[:, linear], interp1d(knot_times, knots[:, linear], axis=0)(times))
    heading = principal_value(interp1d(knot_times, np.unwrap(knots[:, StateIndex.HEADING]))(times))
    np.testing.assert_array_equal(past[:, StateIndex.HEADING], heading)
    x, y = rear_axle_round_trip(
        interp1d(knot_times, knots[:, StateIndex.X])(times),
        interp1d(knot_times, knots[:, StateIndex.Y])(times),
        heading,
    )
    np.testing.assert_array_equal(past[:, : StateIndex.Y + 1], np.stack([x, y], axis=-1))
    assert not past[:, StateIndex.STEERING_ANGLE :].any()
    # 56 states on the 0.1 s grid, filtered as the devkit's call on the pair.
    groups, _ = _groups()
    pair = groups[rows().index(row)]
    np.testing.assert_array_equal(
        history_comfort_checks(comfort_series(pair[None], at_centre=True), [past])[0],
        _devkit_checks(_padded(pair, past)),
    )


def test_the_past_needs_three_frames_and_one_sampled_state() -> None:
    source = scene(rows()[0].scene_path)
    with pytest.raises(ValueError, match="3 past frames"):
        past_states(source._replace(current_index=2))
    squeezed = _jittered(source, (1_400_000, 950_000, 480_000))  # t_-3 is 0.1 s before t_0
    with pytest.raises(ValueError, match="no past state"):
        past_states(squeezed)


def test_tokens_without_a_past_pass_and_past_lengths_batch_apart() -> None:
    groups, pasts = _groups()
    failing = [index for index, row in enumerate(rows()) if row.line["history_comfort"] == 0.0][:3]
    passing = [index for index, row in enumerate(rows()) if row.line["history_comfort"] == 1.0][:2]
    chosen = failing + passing
    longer = past_states(_jittered(scene(rows()[passing[0]].scene_path), (-60_000, 0, 0)))
    mixed = [pasts[failing[0]], None, pasts[failing[2]], longer, pasts[passing[1]]]

    checks = history_comfort_checks(comfort_series(groups[chosen], at_centre=True), mixed)

    assert checks[1].all()  # a failing token without a past passes
    for position, past in enumerate(mixed):
        if past is not None:
            np.testing.assert_array_equal(
                checks[position], _devkit_checks(_padded(groups[chosen[position]], past))
            )
    with pytest.raises(ValueError, match="pasts for"):
        history_comfort_checks(comfort_series(groups[chosen], at_centre=True), mixed[:-1])
