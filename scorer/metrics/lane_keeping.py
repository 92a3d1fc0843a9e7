"""Lane keeping (LK) in {0, 1}, a v2 weighted metric (docs/engine.md, "v2.2: lane keeping").

As `_calculate_lane_keeping`: the box centre's distance to the centerline (shapely `distance` to its
linestring, the devkit's call) is compared with the deviation limit at every time index; LK is 0 once
`ceil(window / 0.1)` consecutive indices lie beyond it. Indices whose centre is inside an intersection
are skipped: they neither count nor reset the run. The devkit walks each proposal in time; here the run
lengths of all rows advance together, one array step per time index.

Only whether a distance exceeds the limit counts, so each row is measured against the run of centerline
segments that come near its centres (`nearby_centerlines`): GEOS's distance is the least of its segments'
distances, and the segments left out are beyond the limit, so the comparison is the same, to the bit.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import shapely

from scorer.geometry import BoolArray, FloatArray, IntArray
from scorer.metrics.ego_box import repeated_from
from scorer.metrics.pairs import same_token_pairs

# A segment left out keeps clear of the row's centres by the limit plus this much of their coordinates' size
# (plus 1 m): far above the rounding of GEOS's point-to-segment distance (a few 2**-53 of that size), so its
# distance as GEOS computes it is beyond the limit too.
CLEARANCE = 2.0**-30


def nearby_centerlines(
    centers: FloatArray, centerlines: npt.NDArray[np.object_], row_token: IntArray, limit: float
) -> npt.NDArray[np.object_]:
    """Return each row's centerline (R,) cut to its segments from the first to the last whose bounds come within
    `limit` (and `CLEARANCE`) of the bounds of the row's centres (R, T, 2); the whole centerline where none does.

    Each centre's distance to it is its distance to the whole centerline wherever either is at most `limit`;
    elsewhere both exceed `limit`.
    """
    coords, owner = shapely.get_coordinates(centerlines, return_index=True)
    vertices = np.bincount(owner, minlength=len(centerlines))
    first_vertex = np.cumsum(vertices) - vertices
    x, y = coords[:, 0], coords[:, 1]
    # Segment i runs from vertex i to i + 1 (the last vertex of a line starts none).
    segment_low_x, segment_high_x = np.minimum(x[:-1], x[1:]), np.maximum(x[:-1], x[1:])
    segment_low_y, segment_high_y = np.minimum(y[:-1], y[1:]), np.maximum(y[:-1], y[1:])
    center_x, center_y = centers[..., 0], centers[..., 1]
    low_x, high_x = center_x.min(axis=1), center_x.max(axis=1)
    low_y, high_y = center_y.min(axis=1), center_y.max(axis=1)
    size = np.maximum(np.maximum(np.abs(low_x), np.abs(high_x)), np.maximum(np.abs(low_y), np.abs(high_y)))
    reach = limit + CLEARANCE * (1.0 + size)
    low_x, high_x, low_y, high_y = low_x - reach, high_x + reach, low_y - reach, high_y + reach
    rows, segments = same_token_pairs(row_token, first_vertex, vertices - 1)
    near = (
        (segment_low_x[segments] <= high_x[rows])
        & (low_x[rows] <= segment_high_x[segments])
        & (segment_low_y[segments] <= high_y[rows])
        & (low_y[rows] <= segment_high_y[segments])
    )
    # Each row's segments are consecutive in `segments`, in order.
    row_segments = (vertices - 1)[row_token]
    row_start = np.cumsum(row_segments) - row_segments
    first = np.minimum.reduceat(np.where(near, segments, np.iinfo(np.intp).max), row_start)
    last = np.maximum.reduceat(np.where(near, segments, -1), row_start)
    whole = last < 0  # no segment near (or no finite centre): the whole centerline, as before
    first[whole] = first_vertex[row_token[whole]]
    last[whole] = (first_vertex + vertices - 2)[row_token[whole]]
    kept = last - first + 2  # vertices
    vertex = np.repeat(first - np.cumsum(kept) + kept, kept) + np.arange(kept.sum())
    return np.asarray(
        shapely.linestrings(coords[vertex], indices=np.repeat(np.arange(len(centers)), kept)), dtype=object
    )


def lane_keeping(
    centers: FloatArray,
    in_intersection: BoolArray,
    centerlines: npt.NDArray[np.object_],
    row_token: IntArray,
    deviation_limit: float,
    window_s: float,
    step_s: float,
) -> tuple[FloatArray, IntArray, IntArray]:
    """Return LK (R,), each row's first failing time index (-1 if none) and its longest run beyond the limit,
    from box centres (R, T, 2), whether each is inside an intersection (R, T), and each token's centerline."""
    required = math.ceil(window_s / step_s)
    nearby = nearby_centerlines(centers, centerlines, row_token, deviation_limit)
    # A centre that repeats the step before's to the bit has its distance.
    measured_step = repeated_from(centers)
    rows, steps = np.nonzero(measured_step == np.arange(centers.shape[1]))
    deviation = np.empty(centers.shape[:2])
    deviation[rows, steps] = shapely.distance(shapely.points(centers[rows, steps]), nearby[rows])
    deviation = deviation[np.arange(len(centers))[:, None], measured_step]
    beyond = (deviation > deviation_limit) & ~in_intersection
    counting = ~in_intersection
    run = np.zeros(len(centers), dtype=np.intp)
    longest = np.zeros(len(centers), dtype=np.intp)
    first_fail = np.full(len(centers), -1, dtype=np.intp)
    for step in range(centers.shape[1]):
        run = np.where(beyond[:, step], run + 1, np.where(counting[:, step], 0, run))
        longest = np.maximum(longest, run)
        first_fail = np.where((first_fail < 0) & (run >= required), step, first_fail)
    return np.where(first_fail >= 0, 0.0, 1.0), first_fail, longest
