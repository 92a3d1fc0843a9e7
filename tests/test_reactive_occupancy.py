"""The reactive simulation's shortcuts against the plain computations they replace, bit for bit: the capsules
of a path ahead and of a footprint's path (slices of a path's memoised segments) against the segments of the
points `to_go` and `between` give, a box polygon's corners against `box_corners`, whether a path ahead meets
a box against GEOS's buffer of it, a path's memoised states against fresh ones and the capsule test's clamped
projection against Python's min and max; and the bounds against
what they bound: a box's capsule holds the box, a box taken as its own simplification is GEOS's, a path ahead
taken to meet the box it starts in meets it."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import shapely

from scorer.geometry import EGO_HALF_LENGTH, EGO_HALF_WIDTH, box_corners
from scorer.reactive.agents import box_polygon
from scorer.reactive.occupancy import (
    BOUND_SLACK,
    BUFFER_REACH,
    SIMPLIFY_TOLERANCE,
    _end_within,
    bound_of,
    box_capsule,
    box_is_simplified,
    capsules_meet,
    path_between_bound,
    path_to_go_bound,
)
from scorer.reactive.paths import LanePath
from scorer.reactive.traffic import _inside_box, _PathAhead

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


def _boxes(count: int, seed: int) -> list[tuple[float, float, float, float, float]]:
    """Boxes (x, y, heading, length, width) at map coordinates, of vehicle sizes and of slivers."""
    rng = np.random.default_rng(seed)
    boxes = []
    for index in range(count):
        x, y = rng.uniform(-7e5, 7e5, 2).tolist()
        heading = float(rng.uniform(-math.pi, math.pi)) if index % 10 else index / 10 * math.pi / 8
        length, width = (10.0 ** rng.uniform(-5.0, 1.5, 2)).tolist()
        boxes.append((x, y, heading, length, width))
    return boxes


def test_a_box_capsule_holds_its_box() -> None:
    for x, y, heading, length, width in _boxes(3000, 17):
        x0, y0, x1, y1, radius = box_capsule(x, y, heading, length, width)
        corners = shapely.points(shapely.get_coordinates(box_polygon(x, y, heading, length, width)))
        reach = shapely.distance(shapely.linestrings([[x0, y0], [x1, y1]]), corners) - radius
        assert reach.max() < BOUND_SLACK / 1000


def test_a_box_taken_as_its_own_simplification_is_it() -> None:
    boxes = _boxes(3000, 19)
    # About the threshold: the corner's height over the diagonal a thousand tolerances, nudged either way.
    for length in (0.011, 0.02, 1.0):
        width = 1 / math.sqrt(1 / (1000 * SIMPLIFY_TOLERANCE) ** 2 - 1 / length**2)
        boxes += [(12.5, -3.0, 0.3, length, math.nextafter(width, side)) for side in (0.0, math.inf)]
    ego = box_corners(664_000.0, 3_997_000.0, 0.7, EGO_HALF_LENGTH, EGO_HALF_WIDTH)
    simplified = 0
    for x, y, heading, length, width in boxes:
        if box_is_simplified(length, width):
            simplified += 1
            box = box_polygon(x, y, heading, length, width)
            once = shapely.simplify(box, SIMPLIFY_TOLERANCE, preserve_topology=True)
            assert shapely.equals_exact(once, box, tolerance=0.0)
    assert 0 < simplified < len(boxes)
    assert box_is_simplified(2 * EGO_HALF_LENGTH, 2 * EGO_HALF_WIDTH)
    ego_box = shapely.polygons(ego)
    assert shapely.equals_exact(shapely.simplify(ego_box, SIMPLIFY_TOLERANCE), ego_box, tolerance=0.0)
    # Where the shortcut does not claim it, simplifying may well change the box.
    sliver = box_polygon(1.0, 2.0, 0.5, 3.0, 1e-6)
    assert not box_is_simplified(3.0, 1e-6)
    assert not shapely.equals_exact(shapely.simplify(sliver, SIMPLIFY_TOLERANCE), sliver, tolerance=0.0)


def test_a_path_ahead_starting_inside_a_box_meets_it() -> None:
    rng = np.random.default_rng(23)
    claimed = refused = 0
    for x, y, heading, length, width in _boxes(400, 29):
        length, width = length + 0.5, width + 0.5
        box = shapely.simplify(box_polygon(x, y, heading, length, width), SIMPLIFY_TOLERANCE)
        cos, sin = math.cos(heading), math.sin(heading)
        # First points about a side, within and beyond the margin, at it and an ulp either side.
        for side, sign, offset in itertools.product(
            ("along", "across"), (-1.0, 1.0), (-2.0, -1.0, -0.5, 0.5, 1.0)
        ):
            half, other = (length / 2, width / 2) if side == "along" else (width / 2, length / 2)
            reach = half + offset * BOUND_SLACK
            for at in (reach, math.nextafter(reach, 0.0), math.nextafter(reach, math.inf)):
                free = float(rng.uniform(-other + 2 * BOUND_SLACK, other - 2 * BOUND_SLACK))
                along, across = (sign * at, free) if side == "along" else (free, sign * at)
                start = (x + along * cos - across * sin, y + along * sin + across * cos)
                # The path ahead leaves through that side.
                outward = heading + (0.0 if side == "along" else math.pi / 2) + (sign < 0) * math.pi
                direction = outward + rng.uniform(-0.3, 0.3)
                second = (start[0] + 0.3 * math.cos(direction), start[1] + 0.3 * math.sin(direction))
                points = np.array([start, second, (second[0] + 1.0, second[1])])
                if not _inside_box(*start, (x, y, heading), length, width):
                    refused += 1
                    continue
                claimed += 1
                # Whatever the buffer's width: narrow, where the box's side alone decides.
                for half_width in (width / 2, 1e-3):
                    buffer = shapely.buffer(shapely.linestrings(points), half_width, cap_style="flat")
                    assert shapely.intersects(box, buffer)
    assert claimed > 1000 and refused > 1000


def test_the_clamped_projection_is_min_and_max() -> None:
    """`_end_within` clamps the projection by comparisons: the same side as min(max(fraction, 0), 1) on every
    pair, NaN, infinite and degenerate segments among them."""
    rng = np.random.default_rng(11)
    values = [*rng.normal(0.0, 3.0, 600).tolist(), 0.0, -0.0, 1e-300, -1e-300, math.inf, -math.inf, math.nan]
    for x, y, x0, y0, dx, dy, signed_reach in rng.choice(values, (20000, 7)).tolist():
        reach = abs(signed_reach)
        squared = dx * dx + dy * dy
        fraction = min(max(((x - x0) * dx + (y - y0) * dy) / (squared if squared > 0 else 1.0), 0.0), 1.0)
        distance = math.hypot(x - x0 - fraction * dx, y - y0 - fraction * dy)
        if abs(distance - reach) <= reach * 1e-9:
            distance = float(np.hypot(x - x0 - fraction * dx, y - y0 - fraction * dy))
        assert _end_within(x, y, x0, y0, dx, dy, squared, reach) == (distance <= reach)


def test_the_capsule_test_meets_what_lies_within_the_reach() -> None:
    """`capsules_meet` (its sides' test refusing a segment wholly beyond the reach on one side of the other's
    line, then the crossing and end tests) says whether the segments lie within the two radii and the slack
    of each other, as GEOS measures their distance: on pairs around the reach (near misses at any angle,
    crossing and degenerate segments)."""
    rng = np.random.default_rng(5)
    x0, y0, length, angle, other_angle, along, radius, other_radius, offset = rng.random((9, 20000))
    first = np.stack([x0, y0, x0 + 4 * length * np.cos(6 * angle), y0 + 4 * length * np.sin(6 * angle)], 1)
    # The second segment starts from 0.99 to 1.01 reaches away from a point of the first, across it.
    reach = radius + other_radius + BOUND_SLACK
    start = first[:, :2] + along[:, None] * (first[:, 2:] - first[:, :2])
    start += ((0.99 + 0.02 * offset) * reach)[:, None] * np.stack([np.sin(6 * angle), -np.cos(6 * angle)], 1)
    other_length = 3 * length * (other_angle > 0.1)  # a tenth of them points
    second = np.hstack(
        [
            start,
            start + other_length[:, None] * np.stack([np.cos(6 * other_angle), np.sin(6 * other_angle)], 1),
        ]
    )
    distance = shapely.distance(
        shapely.linestrings(first.reshape(-1, 2, 2)), shapely.linestrings(second.reshape(-1, 2, 2))
    )
    met = [
        capsules_meet((*a, first_radius), (*b, second_radius), 0.0, 0.0)
        for a, b, first_radius, second_radius in zip(
            first.tolist(), second.tolist(), radius.tolist(), other_radius.tolist(), strict=True
        )
    ]
    assert met == (distance <= reach).tolist()
    assert 1000 < sum(met) < 19000
