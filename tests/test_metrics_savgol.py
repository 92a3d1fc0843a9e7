"""The Savitzky-Golay operators against the installed scipy: bit-identical to `savgol_filter` of the identity."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import savgol_filter

from scorer.metrics.savgol import filter_batch, savgol_operator
from scorer.metrics.savgol import savgol_filter as savgol_filter_of_group

# (n, window, poly_order, deriv, delta): the comfort metric's filters at 41 states and 0.1 s, then others
# (even and odd windows, a window as long as the series, second derivatives, other spacings).
CASES = [
    (41, 41, 2, 0, 1.0),
    (41, 8, 2, 0, 1.0),
    (41, 41, 2, 1, 0.1),
    (41, 5, 3, 2, 0.1),
    (41, 5, 2, 1, 0.1),
    (20, 15, 2, 1, 0.5),
    (9, 4, 3, 3, 0.25),
    (5, 5, 2, 2, 1.0),
    (12, 3, 1, 0, 2.0),
]


@pytest.mark.parametrize(("num_steps", "window", "poly_order", "deriv", "delta"), CASES)
def test_operator_is_scipys_filter_of_the_identity(
    num_steps: int, window: int, poly_order: int, deriv: int, delta: float
) -> None:
    expected = savgol_filter(
        np.eye(num_steps), window_length=window, polyorder=poly_order, deriv=deriv, delta=delta, axis=-1
    )
    np.testing.assert_array_equal(savgol_operator(num_steps, window, poly_order, deriv, delta), expected)


def test_operator_applied_to_a_series_is_the_filter_of_the_series() -> None:
    series = np.random.default_rng(3).normal(size=(6, 41))
    filtered = savgol_filter(series, window_length=8, polyorder=2, axis=-1)
    np.testing.assert_allclose(series @ savgol_operator(41, 8, 2, 0, 1.0), filtered, rtol=0, atol=1e-13)


@pytest.mark.parametrize("group_size", [1, 2, 15])
@pytest.mark.parametrize(("num_steps", "window", "poly_order", "deriv", "delta"), CASES)
def test_group_filter_is_scipys_call_on_the_group(
    group_size: int, num_steps: int, window: int, poly_order: int, deriv: int, delta: float
) -> None:
    rng = np.random.default_rng(group_size * 100 + window)
    for _ in range(20):
        group = rng.normal(0, 3, (group_size, num_steps)) * rng.uniform(0.01, 100, (group_size, 1))
        expected = savgol_filter(group, window_length=window, polyorder=poly_order, deriv=deriv, delta=delta)
        np.testing.assert_array_equal(
            savgol_filter_of_group(group, window, poly_order, deriv, delta), expected
        )


def test_batch_filter_is_exact_inside_and_bounded_at_the_edges() -> None:
    rng = np.random.default_rng(9)
    series = rng.normal(0, 3, (200, 41)) + rng.uniform(-4, 4, (200, 1))
    for window, poly_order, deriv, delta in [(41, 2, 0, 1.0), (8, 2, 0, 1.0), (5, 3, 2, 0.1)]:
        filtered, error = filter_batch(series, window, poly_order, deriv, delta)
        expected = np.concatenate(
            [savgol_filter_of_group(pair, window, poly_order, deriv, delta) for pair in np.split(series, 100)]
        )
        interior = error == 0
        assert interior.sum() == 200 * (41 - 2 * (window // 2))
        np.testing.assert_array_equal(filtered[interior], expected[interior])
        assert (np.abs(filtered - expected) <= error / 4).all()  # with room to spare
