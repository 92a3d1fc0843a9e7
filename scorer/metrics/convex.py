"""Exact intersection tests for boxes (convex quadrilaterals, corners counterclockwise) and segments.

GEOS decides `intersects` exactly on the input doubles: its orientation predicate takes the sign of a
floating-point determinant where an error bound proves it right and recomputes the rest in extended
precision. These tests use the same filter and exact rational arithmetic where it cannot decide, so
they give GEOS's booleans, about a hundred times faster than building polygons for each pair.

Two closed convex polygons meet iff a vertex of one lies in the other (boundary included) or two
edges cross properly: touching edges either cross or overlap along a line, whose ends are vertices.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import numpy.typing as npt

from scorer.geometry import BoolArray, FloatArray

SignArray = npt.NDArray[np.int8]

# GEOS `CGAlgorithmsDD::orientationIndexFilter` (DP_SAFE_EPSILON): a determinant this far from 0,
# relative to its terms, has a certain sign.
SAFE_EPSILON = 1e-15


def _exact_sign(a: FloatArray, b: FloatArray, c: FloatArray) -> int:
    # Loaded only where the filter cannot decide: fractions, with decimal, is 1 ms of a score's start-up.
    from fractions import Fraction

    ax, ay, bx, by, cx, cy = (Fraction(float(value)) for value in (*a, *b, *c))
    determinant = (ax - cx) * (by - cy) - (ay - cy) * (bx - cx)
    return (determinant > 0) - (determinant < 0)


def orientation(a: FloatArray, b: FloatArray, c: FloatArray) -> SignArray:
    """Return the exact side of c relative to the line a -> b (..., 2): 1 left, -1 right, 0 on it."""
    left = (a[..., 0] - c[..., 0]) * (b[..., 1] - c[..., 1])
    right = (a[..., 1] - c[..., 1]) * (b[..., 0] - c[..., 0])
    determinant = left - right
    signs = np.array(np.sign(determinant), dtype=np.int8)
    # Terms of opposite sign (or a zero term) fix the sign; otherwise the error bound must clear it.
    same_sign = ((left > 0) & (right > 0)) | ((left < 0) & (right < 0))
    uncertain = same_sign & (np.abs(determinant) < SAFE_EPSILON * (np.abs(left) + np.abs(right)))
    if uncertain.any():
        a, b, c = (np.broadcast_to(points, (*determinant.shape, 2)) for points in (a, b, c))
        for index in map(tuple, np.argwhere(uncertain)):
            signs[index] = _exact_sign(a[index], b[index], c[index])
    return signs


NEXT = np.array([1, 2, 3, 0])  # the next corner of a quad, i.e. the end of edge i
AFTER_NEXT = np.array([2, 3, 0, 1])


def is_convex_counterclockwise(quads: FloatArray) -> BoolArray:
    """Return whether quads (..., 4, 2) turn strictly left at every corner (a proper counterclockwise box)."""
    turns_left: BoolArray = orientation(quads, quads[..., NEXT, :], quads[..., AFTER_NEXT, :]) > 0
    return cast(BoolArray, turns_left.all(axis=-1))


def _sides(quads: FloatArray, points: FloatArray) -> SignArray:
    """Return the side (..., 4 edges, n points) of each point (..., n, 2) relative to each quad edge."""
    return orientation(quads[..., :, None, :], quads[..., NEXT, None, :], points[..., None, :, :])


def quads_intersect(first: FloatArray, second: FloatArray) -> BoolArray:
    """Return whether closed convex counterclockwise quads (K, 4, 2) intersect; touching counts."""
    pairs = np.stack([first, second], axis=1)  # (K, 2, 4, 2)
    # sides[k, 0, i, j]: vertex j of second against edge i of first; sides[k, 1, j, i] the other way round.
    sides = _sides(pairs, pairs[:, ::-1])
    vertex_inside = np.any(np.all(sides >= 0, axis=2), axis=(1, 2))
    # Edge i of one crosses edge j of the other properly: each separates the other's two ends strictly.
    straddles = sides * sides[..., NEXT] < 0
    crossing = np.any(straddles[:, 0] & straddles[:, 1].transpose(0, 2, 1), axis=(1, 2))
    return cast(BoolArray, vertex_inside | crossing)


def segment_meets_quad(start: FloatArray, end: FloatArray, quads: FloatArray) -> BoolArray:
    """Return whether closed segments (K, 2) -> (K, 2) meet closed convex counterclockwise quads (K, 4, 2)."""
    ends = np.stack([start, end], axis=-2)  # (K, 2, 2)
    end_sides = _sides(quads, ends)  # (K, edge, segment end)
    end_inside = (end_sides >= 0).all(axis=1).any(axis=-1)
    vertex_sides = orientation(start[:, None], end[:, None], quads)  # (K, vertex)
    lower, upper = np.minimum(start, end)[:, None], np.maximum(start, end)[:, None]
    vertex_on_segment = (vertex_sides == 0) & ((lower <= quads) & (quads <= upper)).all(axis=-1)
    edge_straddles = vertex_sides * vertex_sides[:, NEXT] < 0  # quad edge j across the segment's line
    segment_straddles = end_sides[:, :, 0] * end_sides[:, :, 1] < 0  # the segment across edge j's line
    crossing = (edge_straddles & segment_straddles).any(axis=-1)
    return end_inside | vertex_on_segment.any(axis=-1) | crossing
