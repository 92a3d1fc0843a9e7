"""Bounding boxes of box corners, as the pruning of candidate pairs reads them."""

from __future__ import annotations

import numpy as np
import pytest

from scorer.metrics.pairs import corner_bounds


def corner_bounds_pairwise(points: np.ndarray) -> np.ndarray:
    """The bounds as first written: the 4 corners' minima and maxima, x and y side by side."""
    corners = [points[..., index, :] for index in range(4)]
    lower = np.minimum(np.minimum(corners[0], corners[1]), np.minimum(corners[2], corners[3]))
    upper = np.maximum(np.maximum(corners[0], corners[1]), np.maximum(corners[2], corners[3]))
    return np.concatenate([lower, upper], axis=-1)


@pytest.mark.parametrize("shape", [(51, 997, 4, 2), (800, 41, 6, 2), (3, 0, 4, 2), (4, 2), (1, 5, 2)])
def test_corner_bounds_are_the_pairwise_minima_and_maxima_bit_for_bit(shape: tuple[int, ...]) -> None:
    """Tiny, huge, negative, NaN, infinite, subnormal and signed-zero corners, and points past the fourth."""
    rng = np.random.default_rng(3)
    points = rng.standard_normal(shape) * 10.0 ** rng.integers(-320, 308, shape)
    specials = np.array([np.nan, np.inf, -np.inf, 1.7e308, -1.7e308, 5e-324, -5e-324, 0.0, -0.0, 1e-310])
    chosen = rng.random(shape) < 0.1
    points[chosen] = rng.choice(specials, int(chosen.sum()))
    assert corner_bounds(points).tobytes() == corner_bounds_pairwise(points).tobytes()
    # Signed zeros against each other in every corner order.
    zeros = rng.choice([0.0, -0.0], shape)
    assert corner_bounds(zeros).tobytes() == corner_bounds_pairwise(zeros).tobytes()
