"""The reactive loop's GEOS calls made through shapely's compiled functions (scorer.reactive.geos) against the
public shapely calls they stand for, on random geometries of the loop's kinds: the same coordinates to the
bit, the same booleans and distances. They use shapely's private signatures, so a shapely that changes them
fails here."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from scorer.reactive import geos

ORIGIN = np.array([665328.6352374122, 3996354.5321324635])  # UTM-sized coordinates, as in the logs


def _same(first: shapely.Geometry, second: shapely.Geometry) -> bool:
    """Equal to the bit: the same type, structure and coordinates (WKB of full precision)."""
    return bool(shapely.to_wkb(first) == shapely.to_wkb(second))


def _boxes(rng: np.random.Generator, count: int) -> list[list[tuple[float, float]]]:
    boxes = []
    for _ in range(count):
        centre = ORIGIN + rng.uniform(-30.0, 30.0, 2)
        heading, length, width = rng.uniform(-np.pi, np.pi), rng.uniform(3.0, 6.0), rng.uniform(1.5, 2.5)
        along = np.array([np.cos(heading), np.sin(heading)]) * length / 2
        across = np.array([-np.sin(heading), np.cos(heading)]) * width / 2
        corners = [
            centre + along + across,
            centre - along + across,
            centre - along - across,
            centre + along - across,
        ]
        boxes.append([(float(x), float(y)) for x, y in corners])
    return boxes


def _lines(rng: np.random.Generator, count: int) -> list[np.ndarray]:
    lines = []
    for _ in range(count):
        steps = rng.uniform(0.5, 4.0, (int(rng.integers(2, 12)), 1))
        directions = np.cumsum(rng.normal(0.0, 0.4, len(steps)))
        moves = steps * np.stack([np.cos(directions), np.sin(directions)], axis=1)
        lines.append(ORIGIN + rng.uniform(-30.0, 30.0, 2) + np.cumsum(moves, axis=0))
    return lines


@pytest.fixture(scope="module")
def rng() -> np.random.Generator:
    return np.random.default_rng(11)


def test_polygons_and_lines_are_shapelys(rng: np.random.Generator) -> None:
    for corners in _boxes(rng, 200):
        assert _same(geos.polygon(corners), shapely.polygons(np.array(corners)))
    for points in _lines(rng, 200):
        assert _same(geos.line(points), shapely.linestrings(points))


def test_buffers_unions_and_simplifications_are_shapelys(rng: np.random.Generator) -> None:
    for points, corners in zip(_lines(rng, 200), _boxes(rng, 200), strict=True):
        line, box = shapely.linestrings(points), shapely.polygons(np.array(corners))
        half_width = float(rng.uniform(0.5, 1.5))
        ahead = geos.flat_buffer(line, half_width)
        assert _same(ahead, shapely.buffer(line, half_width, cap_style="flat"))
        union = geos.union(ahead, box)
        assert _same(union, shapely.union_all([ahead, box]))
        tolerance = float(rng.uniform(0.01, 0.5))
        assert _same(
            geos.simplify(union, tolerance), shapely.simplify(union, tolerance, preserve_topology=True)
        )


def test_predicates_and_distances_are_shapelys(rng: np.random.Generator) -> None:
    outcomes = set()
    for points, corners in zip(_lines(rng, 300), _boxes(rng, 300), strict=True):
        line, box = shapely.linestrings(points), shapely.polygons(np.array(corners))
        meets = geos.intersects(line, box)
        assert meets == bool(shapely.intersects(line, box))
        outcomes.add(meets)
        assert geos.distance(line, box) == float(shapely.distance(line, box))
        assert geos.equals_exactly(box, shapely.polygons(np.array(corners)))
        assert not geos.equals_exactly(box, shapely.simplify(line, 0.0))
    assert outcomes == {True, False}  # both answers were compared
