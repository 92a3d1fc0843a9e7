"""Candidate pairs within each scene token of a batch, pruned by bounding boxes before any exact test.

Bounding boxes only prune: two geometries that touch have touching boxes, a point strictly inside a
polygon lies inside its box, so the exact shapely test that follows sees every true pair.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import shapely

from scorer.drivable_map import MapBatch
from scorer.geometry import BoolArray, FloatArray, IntArray


def same_token_pairs(row_token: IntArray, start: IntArray, count: IntArray) -> tuple[IntArray, IntArray]:
    """Return every (row, item) with the item among its row's token's items [start, start + count)."""
    counts = count[row_token]
    rows = np.repeat(np.arange(len(row_token)), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    return rows, np.repeat(start[row_token], counts) + offsets


def corner_bounds(points: FloatArray) -> FloatArray:
    """Return the bounding boxes (..., 4) of boxes given by their first 4 points (..., >=4, 2), the corners.

    x and y apart, each a strided array with one value a box: numpy runs an elementwise loop over an innermost
    axis of 2 (x, y together) several times slower."""

    def pick(choose: np.ufunc, coordinate: int) -> FloatArray:
        corners = [points[..., index, coordinate] for index in range(4)]
        return cast(FloatArray, choose(choose(corners[0], corners[1]), choose(corners[2], corners[3])))

    return np.stack(
        [pick(np.minimum, 0), pick(np.minimum, 1), pick(np.maximum, 0), pick(np.maximum, 1)], axis=-1
    )


def extents(bounds: FloatArray) -> FloatArray:
    """Return the bounding box (R, 4) of all boxes (R, ..., 4) of each row."""
    # Each bound's values of a row made contiguous first (R, 4, n): numpy reduces over a short last axis (or
    # across it) about ten times slower.
    by_bound = np.ascontiguousarray(bounds.reshape(len(bounds), -1, 4).transpose(0, 2, 1))
    return np.concatenate([by_bound[:, :2].min(axis=-1), by_bound[:, 2:].max(axis=-1)], axis=-1)


def boxes_touch(first: FloatArray, second: FloatArray) -> BoolArray:
    """Return whether boxes (..., 4) touch or overlap; a NaN box (absent geometry) touches nothing."""
    return (
        (first[..., 0] <= second[..., 2])
        & (second[..., 0] <= first[..., 2])
        & (first[..., 1] <= second[..., 3])
        & (second[..., 1] <= first[..., 3])
    )


def points_inside(x: FloatArray, y: FloatArray, polygon: IntArray, maps: MapBatch) -> BoolArray:
    """Return whether each point lies strictly inside its paired polygon (a boundary point is outside).

    The devkit's `shapely.vectorized.contains` (= `contains_xy`), after a bounding-box prune.
    """
    bounds = maps.bounds[polygon]
    inside = (bounds[:, 0] <= x) & (x <= bounds[:, 2]) & (bounds[:, 1] <= y) & (y <= bounds[:, 3])
    candidates = np.flatnonzero(inside)
    inside[candidates] = shapely.contains_xy(
        maps.polygons_at(polygon[candidates]), x[candidates], y[candidates]
    )
    return inside
