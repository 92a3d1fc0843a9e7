"""Exact intersection tests for boxes (convex quadrilaterals, corners counterclockwise) and segments.

GEOS decides `intersects` exactly on the input doubles: its orientation predicate takes the sign of a
floating-point determinant where an error bound proves it right and recomputes the rest in extended
precision. These tests use the same filter and exact rational arithmetic where it cannot decide, so
they give GEOS's booleans, about a hundred times faster than building polygons for each pair.

Two closed convex polygons meet iff a vertex of one lies in the other (boundary included) or two
edges cross properly: touching edges either cross or overlap along a line, whose ends are vertices.

Most pairs that reach an exact test are apart, and `quads_apart` settles those first with a few array
operations: projected on an edge direction of either quad, their corners lie in two ranges with a gap
wider than the rounding error of the projections, so a line separates them and no exact test is needed.
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


# The gap `quads_apart` requires, relative to |axis|_1 times the corners' reach from the first corner: a
# projection's rounding error is at most 3.1 * 2**-53 of that (2**-53 from the corner's difference, 2**-52
# from the 2-term dot product), and a gap of 2**-44 of it leaves a factor 80 over both ends' errors.
APART_GAP = 2.0**-44
APART_FLOOR = 1e-290  # absolute: what underflowing products can lose


def _low_high(values: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return the least and greatest of 4 rows (4, K), elementwise."""
    low = np.minimum(np.minimum(values[0], values[1]), np.minimum(values[2], values[3]))
    high = np.maximum(np.maximum(values[0], values[1]), np.maximum(values[2], values[3]))
    return low, high


def quads_apart(first: FloatArray, second: FloatArray) -> BoolArray:
    """Return where quads (K, 4, 2) are certainly disjoint: their corners are separated, with more than the
    rounding error to spare, along the direction of edge 0 or 1 of either quad (the axes of two boxes).

    A line then separates the corners, hence the quads (each lies in its corners' convex hull, whatever its
    shape), so GEOS's `intersects` is False too. False where in doubt or not finite; a pair not found apart
    may still be disjoint.
    """
    # Corner-major rows (8, K), relative to the first quad's first corner.
    x = np.concatenate([first[..., 0].T, second[..., 0].T])
    y = np.concatenate([first[..., 1].T, second[..., 1].T])
    x, y = x - x[0], y - y[0]
    reach = np.maximum(np.abs(x).max(axis=0), np.abs(y).max(axis=0))
    apart = np.zeros(len(first), dtype=bool)
    for start, end in ((0, 1), (1, 2), (4, 5), (5, 6)):
        axis_x, axis_y = x[end] - x[start], y[end] - y[start]
        projections = x * axis_x + y * axis_y
        gap = APART_GAP * reach * (np.abs(axis_x) + np.abs(axis_y)) + APART_FLOOR
        first_low, first_high = _low_high(projections[:4])
        second_low, second_high = _low_high(projections[4:])
        apart |= (second_low - first_high > gap) | (first_low - second_high > gap)
    return apart


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
