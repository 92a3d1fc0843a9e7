"""The exact box tests give shapely's (GEOS's) booleans, knife edges included."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from scorer.geometry import box_corners
from scorer.metrics.convex import (
    is_convex_counterclockwise,
    orientation,
    quads_apart,
    quads_intersect,
    segment_meets_quad,
)

ORIGIN = np.array([665328.6352374122, 3996354.5321324635])  # UTM-sized coordinates, as in the logs


def boxes(rng: np.random.Generator, count: int, spread: float) -> np.ndarray:
    centers = ORIGIN + rng.uniform(-spread, spread, (count, 2))
    return box_corners(
        centers[:, 0],
        centers[:, 1],
        rng.uniform(-np.pi, np.pi, count),
        rng.uniform(0.2, 3.0, count),
        rng.uniform(0.2, 1.5, count),
    )


def shapely_meets(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    return shapely.intersects(shapely.polygons(first), shapely.polygons(second))


def test_random_boxes_meet_exactly_when_shapely_says_so() -> None:
    rng = np.random.default_rng(7)
    first, second = boxes(rng, 20000, 4.0), boxes(rng, 20000, 4.0)
    expected = shapely_meets(first, second)
    assert 0.2 < expected.mean() < 0.8
    assert np.array_equal(quads_intersect(first, second), expected)


def test_touching_and_nearly_touching_boxes() -> None:
    # Axis-aligned unit boxes sharing an edge or a corner, then moved apart or together by one ulp.
    base = np.array([[1.0, 1.0], [0.0, 1.0], [0.0, 0.0], [1.0, 0.0]]) + ORIGIN
    shifts = [(1.0, 0.0), (1.0, 1.0), (0.5, 1.0), (1.0, 0.25)]
    pairs = []
    for dx, dy in shifts:
        for nudge in (-1, 0, 1):
            other = base + np.array([dx, dy])
            other[:, 0] = np.nextafter(other[:, 0], np.inf * nudge) if nudge else other[:, 0]
            pairs.append((base, other))
    first, second = (np.array(column) for column in zip(*pairs, strict=True))
    expected = shapely_meets(first, second)
    assert expected.sum() >= 4  # exact contacts touch
    assert np.array_equal(quads_intersect(first, second), expected)


def test_a_rotated_box_touching_another_with_a_corner() -> None:
    rng = np.random.default_rng(11)
    first = boxes(rng, 2000, 0.0)
    # Put a second box's corner exactly on the first box's front-left corner.
    second = boxes(rng, 2000, 0.0)
    second += (first[:, 0] - second[:, 2])[:, None, :]
    assert np.array_equal(quads_intersect(first, second), shapely_meets(first, second))


def test_segments_meet_quads_as_shapely_says() -> None:
    rng = np.random.default_rng(3)
    quads = boxes(rng, 20000, 3.0)
    start = ORIGIN + rng.uniform(-4.0, 4.0, (20000, 2))
    end = start + rng.uniform(-3.0, 3.0, (20000, 2))
    # Some segments end exactly on a box corner or run along an edge.
    start[::5], end[::5] = quads[::5, 0], quads[::5, 3]
    end[1::5] = quads[1::5, 1]
    expected = shapely.intersects(
        shapely.linestrings(np.stack([start, end], axis=1)), shapely.polygons(quads)
    )
    assert np.array_equal(segment_meets_quad(start, end, quads), expected)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=6, max_size=6), st.integers(-3, 3))
def test_orientation_is_the_exact_sign(values: list[float], scale: int) -> None:
    a, b = np.array(values[:2]) + ORIGIN, np.array(values[2:4]) + ORIGIN
    # c on the line a -> b up to rounding: where floating point cannot decide the sign.
    c = a + (b - a) * (values[4] % 1.0) + values[5] * 10.0**scale * 1e-12
    exact = (Fraction(b[0]) - Fraction(a[0])) * (Fraction(c[1]) - Fraction(a[1])) - (
        Fraction(b[1]) - Fraction(a[1])
    ) * (Fraction(c[0]) - Fraction(a[0]))
    assert orientation(a, b, c) == (exact > 0) - (exact < 0)


def test_only_proper_counterclockwise_boxes_are_convex() -> None:
    box = box_corners(0.0, 0.0, 0.3, 2.0, 1.0)
    assert is_convex_counterclockwise(box)
    assert not is_convex_counterclockwise(box[::-1])
    flat = box.copy()
    flat[1] = (flat[0] + flat[2]) / 2.0
    assert not is_convex_counterclockwise(flat)


def test_boxes_found_apart_are_disjoint_for_shapely() -> None:
    rng = np.random.default_rng(5)
    first, second = boxes(rng, 20000, 4.0), boxes(rng, 20000, 4.0)
    meet = shapely_meets(first, second)
    apart = quads_apart(first, second)
    assert not (apart & meet).any()
    # An axis of one of two rectangles separates them whenever they are disjoint (up to the rounding gap).
    assert apart.sum() >= 0.99 * (~meet).sum()


def test_boxes_a_rounding_error_apart_are_left_to_the_exact_test() -> None:
    # A second box with a corner on the first's edge 0 or 1 (or at its corner), then pushed out along
    # that edge's outward normal by 0 to 1e-6 m: from ulps, where only the exact test decides, to clear gaps.
    rng = np.random.default_rng(13)
    count = 6000
    first, second = boxes(rng, count, 0.0), boxes(rng, count, 0.0)
    edge = rng.integers(0, 2, count)
    rows = np.arange(count)
    start, end = first[rows, edge], first[rows, edge + 1]
    along = rng.choice([0.0, 0.3, 0.5, 1.0], count)
    normal = np.stack([end[:, 1] - start[:, 1], start[:, 0] - end[:, 0]], axis=1)  # outward: boxes run ccw
    normal /= np.hypot(normal[:, 0], normal[:, 1])[:, None]
    gap = rng.choice([0.0, 1e-15, 1e-12, 1e-10, 1e-9, 1e-6], count) * rng.choice([-1.0, 1.0], count)
    touching = start + (end - start) * along[:, None] + normal * gap[:, None]
    # The corner of the second box that lies furthest against the normal touches the first box's edge.
    nearest = np.argmin(np.einsum("kcd,kd->kc", second, normal), axis=1)
    second += (touching - second[rows, nearest])[:, None, :]
    meet = shapely_meets(first, second)
    apart = quads_apart(first, second)
    assert meet.sum() > count // 4
    assert not (apart & meet).any()
    assert apart[gap >= 1e-9].mean() > 0.9
