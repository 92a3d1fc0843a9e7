"""The reactive simulation's shortcuts against the plain computations they replace, bit for bit: the capsules
of a path ahead and of a footprint's path (slices of a path's memoised segments) against the segments of the
points `to_go` and `between` give, a box polygon's corners against `box_corners`, whether a path ahead meets
a box against GEOS's buffer of it, and a path's memoised states against fresh ones."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import shapely

from scorer.geometry import box_corners
from scorer.reactive.agents import box_polygon
from scorer.reactive.occupancy import BUFFER_REACH, bound_of, path_between_bound, path_to_go_bound
from scorer.reactive.paths import LanePath
from scorer.reactive.traffic import _PathAhead

HALF_WIDTH = 0.9


def _paths() -> list[LanePath]:
    rng = np.random.default_rng(7)
    paths = []
    for vertices in (3, 4, 12, 40):
        directions = np.cumsum(rng.normal(0.0, 0.3, vertices - 1))
        lengths = rng.uniform(0.2, 3.0, (vertices - 1, 1))
        steps = lengths * np.stack([np.cos(directions), np.sin(directions)], axis=1)
        baseline = np.concatenate([[[500.0, -200.0]], [500.0, -200.0] + np.cumsum(steps, axis=0)])
        paths.append(LanePath.of_baseline(baseline))
    return paths


def _progresses(path: LanePath) -> list[float]:
    """Progress values before, on, between and past the path's vertices."""
    middles = [(low + high) / 2 for low, high in itertools.pairwise(path.progress)]
    return [-1.0, *path.progress, *middles, path.end + 1.0, math.nextafter(path.end, 0.0)]


def _segments(points: np.ndarray) -> list[tuple[float, float, float, float, float]]:
    radius = HALF_WIDTH * BUFFER_REACH
    return [(x0, y0, x1, y1, radius) for (x0, y0), (x1, y1) in itertools.pairwise(points.tolist())]


@pytest.mark.parametrize("path", _paths(), ids=lambda path: f"{len(path.progress)}-vertices")
def test_the_path_ahead_bound_is_the_segments_of_to_go(path: LanePath) -> None:
    for progress in _progresses(path):
        clamped = path.clamp(progress)
        assert path_to_go_bound(path, clamped, HALF_WIDTH) == bound_of(_segments(path.to_go(clamped)))


@pytest.mark.parametrize("path", _paths(), ids=lambda path: f"{len(path.progress)}-vertices")
def test_the_footprint_path_bound_is_the_segments_of_between(path: LanePath) -> None:
    for start, end in itertools.product(_progresses(path), repeat=2):
        lower, upper = path.clamp(start), path.clamp(end)
        assert path_between_bound(path, lower, upper, HALF_WIDTH) == bound_of(
            _segments(path.between(lower, upper))
        )


def test_box_polygons_are_box_corners_bit_for_bit() -> None:
    rng = np.random.default_rng(11)
    headings = [*rng.uniform(-7.0, 7.0, 2000), *(quarter * math.pi / 2 for quarter in range(-4, 5)), -0.0]
    for heading in headings:
        x, y = rng.uniform(-1e4, 1e4, 2).tolist()
        length, width = rng.uniform(0.5, 20.0, 2).tolist()
        expected = shapely.polygons(box_corners(x, y, heading, length / 2.0, width / 2.0))
        polygon = box_polygon(x, y, float(heading), length, width)
        assert shapely.get_coordinates(polygon).tobytes() == shapely.get_coordinates(expected).tobytes()


@pytest.mark.parametrize("path", _paths(), ids=lambda path: f"{len(path.progress)}-vertices")
def test_a_path_ahead_meets_what_its_buffer_meets(path: LanePath) -> None:
    rng = np.random.default_rng(13)
    for progress in _progresses(path):
        points = path.to_go(path.clamp(progress))
        buffer = shapely.buffer(shapely.linestrings(points), HALF_WIDTH, cap_style="flat")
        ahead = _PathAhead(points, HALF_WIDTH)
        # Boxes about the path ahead's points and beyond its ends, their sides near the buffer's edge.
        for _ in range(200):
            x, y = points[rng.integers(len(points))] + rng.normal(0.0, 1.5, 2)
            length, width = rng.uniform(0.2, 4.0, 2).tolist()
            box = box_polygon(float(x), float(y), float(rng.uniform(-math.pi, math.pi)), length, width)
            assert ahead.meets(box) == shapely.intersects(box, buffer)


@pytest.mark.parametrize("path", _paths(), ids=lambda path: f"{len(path.progress)}-vertices")
def test_memoised_states_are_fresh_ones(path: LanePath) -> None:
    progresses = _progresses(path) * 3
    states = [path.state_at(progress) for progress in progresses]
    assert states == [
        LanePath(path.progress, path.points, path.unwrapped_heading).state_at(p) for p in progresses
    ]
