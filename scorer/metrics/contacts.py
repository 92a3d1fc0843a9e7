"""Contacts between ego boxes and observed objects, and the ignore-lists NC and TTC share
(docs/engine.md, "Metrics").

The devkit walks time in order and keeps, per proposal, a list of tokens to ignore: a contact that is
not at fault puts its token on the list for the rest of the horizon. Resolved on arrays, an at-fault
contact counts iff it comes before the first not-at-fault contact of the same (proposal, object).
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
from typing import NamedTuple, cast

import numpy as np
import numpy.typing as npt
import shapely

from scorer.geometry import BoolArray, FloatArray, IntArray
from scorer.metrics.convex import (
    is_convex_counterclockwise,
    quads_apart,
    quads_intersect,
    segment_meets_quad,
)
from scorer.metrics.pairs import boxes_touch, corner_bounds, extents, same_token_pairs
from scorer.observation import ObservationBatch
from scorer.svml_acos import arccos_avx512

AHEAD_ANGLE = float(np.deg2rad(30.0))  # nuPlan `is_agent_ahead`
BEHIND_ANGLE = float(np.deg2rad(150.0))  # nuPlan `is_agent_behind`


class Contacts(NamedTuple):
    """Intersecting (ego box, object) pairs; touching counts."""

    row: IntArray  # (K,) proposal row
    step: IntArray  # (K,) box index along the row's second axis
    obj: IntArray  # (K,) object column in the observation batch
    polygons: npt.NDArray[np.object_]  # (K,) the object's box polygon in the queried map
    corners: FloatArray  # (K, 4, 2) its box corners


def find_contacts(
    corners: FloatArray,
    box_bounds: FloatArray,
    map_index: IntArray,
    row_token: IntArray,
    observations: ObservationBatch,
) -> Contacts:
    """Return the contacts of ego boxes (R, S, 4, 2) with their bounds (R, S, 4): box (r, s) against occupancy
    map `map_index[s]` of row r's token. Red-light tokens are left out (the devkit skips them before anything
    else).
    """
    rows, objects = same_token_pairs(row_token, observations.start, observations.counts)
    near = (
        boxes_touch(extents(box_bounds)[rows], observations.extent[objects])
        & ~observations.is_red_light[objects]
    )
    rows, objects = rows[near], objects[near]
    # Bounds of the objects left, at every time index up to the last tested (v1's NC and TTC test 41 of its
    # 51), each box once, then per pair and box (pairs, S, 4).
    near_objects, column = np.unique(objects, return_inverse=True)
    tested = observations.corners[: map_index.max(initial=-1) + 1, near_objects]
    object_bounds = corner_bounds(tested)[map_index[None, :], column[:, None]]
    pair, step = np.nonzero(boxes_touch(box_bounds[rows], object_bounds))
    if not len(pair):
        return Contacts(
            row=pair, step=step, obj=pair, polygons=np.empty(0, dtype=object), corners=np.empty((0, 4, 2))
        )
    row, obj = rows[pair], objects[pair]
    object_corners = observations.corners[map_index[step], obj]
    ego_corners = corners[row, step]
    # Most boxes whose bounds touch are apart along an axis of either box; the others get the exact test.
    hit = ~quads_apart(ego_corners, object_corners)
    hit[hit] = _boxes_meet(ego_corners[hit], object_corners[hit])
    return Contacts(
        row=row[hit],
        step=step[hit],
        obj=obj[hit],
        polygons=shapely.polygons(object_corners[hit]),
        corners=object_corners[hit],
    )


def _exact_pairs(ego_corners: FloatArray, object_corners: FloatArray) -> BoolArray:
    """Return which pairs the exact box tests can take: both proper counterclockwise boxes."""
    valid = cast(BoolArray, np.isfinite(object_corners).all(axis=(-2, -1)))
    valid[valid] = is_convex_counterclockwise(
        np.stack([ego_corners[valid], object_corners[valid]], axis=1)
    ).all(axis=1)
    return valid


def _boxes_meet(ego_corners: FloatArray, object_corners: FloatArray) -> BoolArray:
    """Return whether ego boxes (K, 4, 2) meet object boxes (exact box test, else shapely, whose polygon
    from the 4 corners is the devkit's ring FL, RL, RR, FR, FL)."""
    exact = _exact_pairs(ego_corners, object_corners)
    meet = np.empty(len(object_corners), dtype=bool)
    meet[exact] = quads_intersect(ego_corners[exact], object_corners[exact])
    meet[~exact] = shapely.intersects(
        shapely.polygons(ego_corners[~exact]), shapely.polygons(object_corners[~exact])
    )
    return meet


def segments_meet(
    start: FloatArray, end: FloatArray, ego_corners: FloatArray, contacts: Contacts
) -> BoolArray:
    """Return whether segments (K, 2) -> (K, 2) of the contacts' ego boxes meet the contacted objects."""
    exact = _exact_pairs(ego_corners, contacts.corners)
    meet = np.empty(len(start), dtype=bool)
    meet[exact] = segment_meets_quad(start[exact], end[exact], contacts.corners[exact])
    segments = shapely.linestrings(np.stack([start[~exact], end[~exact]], axis=1))
    meet[~exact] = shapely.intersects(segments, contacts.polygons[~exact])
    return meet


def relative_angle(rear_axle: FloatArray, targets: FloatArray) -> FloatArray:
    """Return the angle (K,) between the ego heading (rear axle x, y, heading (K, 3)) and the direction to
    each target (K, 2), as nuPlan's `get_agent_relative_angle` computes it (docs/engine.md, "BLAS").

    The devkit takes `np.dot` of two 2-vectors and `np.linalg.norm` of one; both are BLAS `ddot`, whose
    rounding belongs to the OpenBLAS kernel. For a target almost exactly behind, that last bit decides
    whether the dot product passes -1 (arccos NaN: "behind" and "ahead" are both false) or not, so each
    contact makes the same `ddot` calls on the same 2-vectors rather than an array expression (`contact_sides`
    asks it only where the comparisons hang on such bits). The heading vectors' cosines and sines are taken on
    arrays (numpy's elementwise loops give each value the bits of its scalar call), and the norm as
    `np.linalg.norm` takes it of a 1-D vector, the square root of the vector dotted with itself: the calls
    left per contact are the two `ddot`s and a division. A target on the rear axle gives NaN too (0 / 0), as
    in the devkit.
    """
    cosines = np.empty(len(targets))
    offsets = targets - rear_axle[:, :2]  # elementwise, as the devkit's scalar differences
    heading_vectors = np.stack([np.cos(rear_axle[:, 2]), np.sin(rear_axle[:, 2])], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        for contact, (offset, heading_vector) in enumerate(zip(offsets, heading_vectors, strict=True)):
            cosines[contact] = heading_vector.dot(offset / np.sqrt(offset.dot(offset)))
        return arccos_avx512(cosines)  # SVML's, as the devkit's numpy on AVX-512 (`scorer.svml_acos`)


# How far from a threshold's cosine (and from +-1) the array arithmetic of `contact_sides` decides a side.
SIDE_MARGIN = 1e-12
_AHEAD_COSINE = float(np.cos(AHEAD_ANGLE))
_BEHIND_COSINE = float(np.cos(BEHIND_ANGLE))


def contact_sides(rear_axle: FloatArray, targets: FloatArray) -> tuple[BoolArray, BoolArray]:
    """Return whether each target (K, 2) is ahead of the ego (rear axle x, y, heading (K, 3)) and whether it is
    behind: `relative_angle`'s angle < AHEAD_ANGLE and > BEHIND_ANGLE (both False where it is NaN), to the bit
    of those comparisons, with `relative_angle`'s per-contact BLAS calls only for the few contacts near a tie.

    The others are decided on arrays by the cosine c' = (cos h dx + sin h dy) / hypot(dx, dy). Proof that such a
    decision is the devkit's: c' and the devkit's cosine c (its heading vector dotted with the offset over its
    norm: two `ddot`s, a square root and a division) each lie within 20 eps (4.5e-15) of the true cosine: the
    heading's cosine and sine are within a few ulps, every other operation rounds once (a fused multiply-add
    once), and the operands are at most 1 in magnitude once divided by the norm. A decided contact has c' more
    than SIDE_MARGIN (1e-12) from the cosine of each threshold angle (the rounded cos, within an ulp of the
    true one) and |c'| < 1 - SIDE_MARGIN; so c lies in (-1, 1) (no NaN), on the side of c', more than 1e-12 -
    1e-14 from the threshold's cosine. arccos has slope at least 1 in magnitude, so the true arccos(c) lies
    that far from the threshold angle: hundreds of times the error of the AVX-512 arccos (`scorer.svml_acos`, a
    few ulps of an angle below 4). The devkit's comparison falls as c' says. The rest (near a tie, the target
    on the rear axle: 0 / 0, a non-finite value) take the exact calls.
    """
    offsets = targets - rear_axle[:, :2]
    heading = rear_axle[:, 2]
    distance = np.hypot(offsets[:, 0], offsets[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        cosines = (np.cos(heading) * offsets[:, 0] + np.sin(heading) * offsets[:, 1]) / distance
    ahead, behind = cosines > _AHEAD_COSINE, cosines < _BEHIND_COSINE
    # NaN fails every comparison, so it goes to the exact calls; so do distances whose squares (the devkit's
    # norm) could underflow or overflow, where the rounding above does not bound its cosine.
    decided = (np.abs(cosines) < 1.0 - SIDE_MARGIN) & (distance > 1e-100) & (distance < 1e100)
    decided &= (np.abs(cosines - _AHEAD_COSINE) > SIDE_MARGIN) & (
        np.abs(cosines - _BEHIND_COSINE) > SIDE_MARGIN
    )
    near = ~decided
    if near.any():
        angles = relative_angle(rear_axle[near], targets[near])
        ahead[near], behind[near] = angles < AHEAD_ANGLE, angles > BEHIND_ANGLE
    return ahead, behind


def centroids(polygons: npt.NDArray[np.object_]) -> FloatArray:
    """Return the polygon centroids (K, 2)."""
    return shapely.get_coordinates(shapely.centroid(polygons)).reshape(-1, 2)


def counted_contacts(row: IntArray, obj: IntArray, order: IntArray, at_fault: BoolArray) -> BoolArray:
    """Return which contacts count: at fault and earlier (by `order`) than any not-at-fault contact of the
    same (row, object), whose token the devkit would have put on that proposal's ignore-list.
    """
    keys, pair = np.unique(row * (obj.max(initial=0) + 1) + obj, return_inverse=True)
    first_cleared = np.full(len(keys), np.inf)
    np.minimum.at(first_cleared, pair[~at_fault], order[~at_fault])
    return at_fault & (order < first_cleared[pair])


class FirstInfraction(NamedTuple):
    """Each row's first counted contact: its time index and object column, -1 where there is none."""

    time_index: IntArray  # (R,)
    obj: IntArray  # (R,) column in the observation batch


def no_contacts(num_rows: int) -> tuple[FloatArray, FirstInfraction]:
    """Return the scores (1) and first infractions (none) of rows without any contact."""
    none = np.full(num_rows, -1, dtype=np.intp)
    return np.ones(num_rows), FirstInfraction(none, none.copy())


def first_infraction(
    row: IntArray, time_index: IntArray, obj: IntArray, counted: BoolArray, num_rows: int
) -> FirstInfraction:
    """Return each row's earliest time index among counted contacts, and the object of that contact (the
    lowest object column when several objects are hit at that time)."""
    row, time_index, obj = row[counted], time_index[counted], obj[counted]
    first = np.full(num_rows, -1, dtype=np.intp)
    first_obj = np.full(num_rows, -1, dtype=np.intp)
    order = np.lexsort((obj, time_index, row))
    rows, starts = np.unique(row[order], return_index=True)
    first[rows] = time_index[order][starts]
    first_obj[rows] = obj[order][starts]
    return FirstInfraction(first, first_obj)
