"""Traffic-light compliance (TLC) in {0, 1}, a v2 multiplier (docs/engine.md, "v2.2: traffic-light compliance").

As `_calculate_traffic_light_compliance`: 0 when the ego polygon touches (`intersects`) a red-light polygon
of the occupancy map at any time index, t = 0 included: an ego that starts on a red connector fails, there
is no ignore-list. Lights are few and mostly absent, so pairs are pruned by bounding boxes over all steps,
then per step, and only the remaining (state, light) pairs get an exact shapely test.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import shapely

from scorer.geometry import FloatArray, IntArray
from scorer.metrics.pairs import boxes_touch, extents, same_token_pairs
from scorer.red_lights import RedLights


def traffic_light_compliance(
    corners: FloatArray, box_bounds: FloatArray, row_token: IntArray, red_lights: Sequence[RedLights | None]
) -> tuple[FloatArray, IntArray, IntArray]:
    """Return TLC (R,) of ego boxes (R, T, 4, 2) with their bounds (R, T, 4) against each row's token's red
    lights, and each row's first contact: its time index and the light's index in the token's red lights (-1
    and -1 if none)."""
    num_rows, num_steps = corners.shape[:2]
    lights = [lights if lights is not None else RedLights.none(num_steps) for lights in red_lights]
    count = np.array([len(light.lane_ids) for light in lights], dtype=np.intp)
    start = np.cumsum(count) - count
    scores = np.ones(num_rows)
    first_index = np.full(num_rows, -1, dtype=np.intp)
    first_light = np.full(num_rows, -1, dtype=np.intp)
    if not count.sum():
        return scores, first_index, first_light
    polygons = np.concatenate([light.polygons for light in lights])
    bounds = np.concatenate([light.bounds for light in lights])
    present = np.concatenate([light.present[:num_steps] for light in lights], axis=1)  # (T, N)

    rows, items = same_token_pairs(row_token, start, count)
    near = boxes_touch(extents(box_bounds)[rows], bounds[items])
    rows, items = rows[near], items[near]
    pair, step = np.nonzero(boxes_touch(box_bounds[rows], bounds[items][:, None]) & present.T[items])
    row, item = rows[pair], items[pair]
    hit = shapely.intersects(shapely.polygons(corners[row, step]), polygons[item])
    row, step, item = row[hit], step[hit], item[hit]
    scores[row] = 0.0
    # The first contact: earliest step, then the light's place in the map (its file order).
    order = np.lexsort((item, step, row))
    row, step, item = row[order], step[order], item[order]
    hit_rows, first = np.unique(row, return_index=True)
    first_index[hit_rows] = step[first]
    first_light[hit_rows] = item[first] - start[row_token[hit_rows]]
    return scores, first_index, first_light
