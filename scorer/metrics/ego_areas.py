"""Where the ego box is at each state: across lanes, off the drivable area, off the route.

See docs/engine.md, "Metrics" (the three flags) and "Drivable-area map" (which polygons count).
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
import shapely

from scorer.drivable_map import MapBatch
from scorer.geometry import BoolArray, FloatArray, IntArray
from scorer.metrics.ego_box import BoxPoint, repeated_from
from scorer.metrics.pairs import boxes_touch, extents, points_inside, same_token_pairs

CORNERS = int(BoxPoint.CENTER)  # points 0..3 are the corners


class EgoArea(IntEnum):
    """Columns of the ego-area array (PDM's `EgoAreaIndex`)."""

    MULTIPLE_LANES = 0
    NON_DRIVABLE_AREA = 1
    ONCOMING_TRAFFIC = 2


def ego_areas(points: FloatArray, bounds: FloatArray, row_token: IntArray, maps: MapBatch) -> BoolArray:
    """Return the ego-area flags (R, T, 3) of ego box points (R, T, 5, 2) with the boxes' bounds (R, T, 4)
    (`_calculate_ego_area`).

    MULTIPLE_LANES: more than one lane polygon holds a corner and none holds all four (the centre is not
    used). NON_DRIVABLE_AREA: some corner is in no roadblock, intersection or car park (lane polygons
    are not drivable). ONCOMING_TRAFFIC: the centre is in no on-route lane, off the road included.
    Containment is strict: a point on a boundary is outside.

    A box whose points repeat the step before's to the bit (a proposal standing still) takes that step's
    flags, which read nothing else of the row: only the other boxes are tested.
    """
    num_rows, num_steps, num_points = points.shape[:3]
    tested_step = repeated_from(points)
    rows, polygons = same_token_pairs(row_token, maps.start, maps.counts)
    near = boxes_touch(extents(bounds)[rows], maps.bounds[polygons])
    near &= (maps.is_lane | maps.is_drivable)[polygons]
    rows, polygons = rows[near], polygons[near]
    # Then per state (the centre lies within the box's bounds), then per point: only points of states whose
    # box touches the polygon's box, and of those only the points within the polygon's box (a point strictly
    # inside lies within it), go to GEOS.
    starts = tested_step == np.arange(num_steps)
    pair, step = np.nonzero(boxes_touch(bounds[rows], maps.bounds[polygons][:, None]) & starts[rows])
    x, y = (points[rows[pair], step, :, axis] for axis in range(2))  # (pairs, 5) each
    box = maps.bounds[polygons[pair]]
    tested = (box[:, :1] <= x) & (x <= box[:, 2:3]) & (box[:, 1:2] <= y) & (y <= box[:, 3:])
    # The centre decides ONCOMING_TRAFFIC alone, which reads on-route lanes only: no other polygon needs it.
    tested[:, CORNERS] &= maps.is_route[polygons[pair]]
    flat = np.flatnonzero(tested)
    candidate, point = np.divmod(flat, num_points)
    inside = shapely.contains_xy(
        maps.polygons_at(polygons[pair[candidate]]), x.reshape(-1)[flat], y.reshape(-1)[flat]
    )
    candidate, point = candidate[inside], point[inside]
    pair, step = pair[candidate], step[candidate]
    row, polygon = rows[pair], polygons[pair]
    corner = point < CORNERS

    on_drivable = np.zeros((num_rows, num_steps, CORNERS), dtype=bool)
    drivable = corner & maps.is_drivable[polygon]
    on_drivable[row[drivable], step[drivable], point[drivable]] = True

    lane = corner & maps.is_lane[polygon]
    corners_in_lane = np.bincount(pair[lane] * num_steps + step[lane], minlength=len(rows) * num_steps)
    state_of_pair = (rows[:, None] * num_steps + np.arange(num_steps)).reshape(-1)
    lanes_touched = np.bincount(state_of_pair, corners_in_lane > 0, minlength=num_rows * num_steps)
    within_one_lane = (
        np.bincount(state_of_pair, corners_in_lane == CORNERS, minlength=num_rows * num_steps) > 0
    )

    on_route = np.zeros((num_rows, num_steps), dtype=bool)
    route = ~corner & maps.is_route[polygon]
    on_route[row[route], step[route]] = True

    areas = np.zeros((num_rows, num_steps, len(EgoArea)), dtype=bool)
    areas[..., EgoArea.MULTIPLE_LANES] = ((lanes_touched > 1) & ~within_one_lane).reshape(num_rows, num_steps)
    areas[..., EgoArea.NON_DRIVABLE_AREA] = ~on_drivable.all(axis=-1)
    areas[..., EgoArea.ONCOMING_TRAFFIC] = ~on_route
    return areas[np.arange(num_rows)[:, None], tested_step]


def in_intersection(x: FloatArray, y: FloatArray, token: IntArray, maps: MapBatch) -> BoolArray:
    """Return whether each point lies strictly inside an intersection of its token's map (`is_in_layer`:
    an STRtree query with predicate `within`, so a point on the boundary is outside)."""
    points, polygons = same_token_pairs(token, maps.start, maps.counts)
    layer = maps.is_intersection[polygons]
    points, polygons = points[layer], polygons[layer]
    inside = np.zeros(len(token), dtype=bool)
    inside[points[points_inside(x[points], y[points], polygons, maps)]] = True
    return inside
