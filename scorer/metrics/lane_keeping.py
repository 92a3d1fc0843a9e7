"""Lane keeping (LK) in {0, 1}, a v2 weighted metric (docs/engine.md, "v2.2: lane keeping").

As `_calculate_lane_keeping`: the box centre's distance to the centerline (shapely `distance` to its
linestring, the devkit's call) is compared with the deviation limit at every time index; LK is 0 once
`ceil(window / 0.1)` consecutive indices lie beyond it. Indices whose centre is inside an intersection
are skipped: they neither count nor reset the run. The devkit walks each proposal in time; here the run
lengths of all rows advance together, one array step per time index.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import shapely

from scorer.geometry import BoolArray, FloatArray, IntArray


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
    deviation = shapely.distance(shapely.points(centers), centerlines[row_token][:, None])
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
