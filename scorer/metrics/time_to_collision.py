"""Time to collision within bound (TTC) in {0, 1}, a weighted metric (docs/engine.md, "Metrics").

At every time index k the ego box is pushed along its heading by |v| * dt for dt = 0, 0.3, 0.6 and
0.9 s and tested against the occupancy map at k + dt. A contact counts when the object is ahead
(within 30 degrees of the heading, seen from the rear axle), or when it is not behind while the ego
straddles lanes, is off the drivable area or has its rear axle strictly inside an intersection. Other
contacts put the token on the proposal's own ignore-list (separate from NC's), in the devkit's order
(time index, then projection). States slower than the stopped-speed threshold are skipped entirely.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from scorer.drivable_map import MapBatch
from scorer.geometry import FloatArray, IntArray
from scorer.metrics.contacts import (
    FirstInfraction,
    centroids,
    contact_sides,
    counted_contacts,
    find_contacts,
    first_infraction,
    no_contacts,
)
from scorer.metrics.ego_areas import EgoArea, in_intersection
from scorer.metrics.ego_box import ego_corners
from scorer.observation import ObservationBatch
from scorer.trajectory import StateIndex

PROJECTION_STEPS = np.arange(0, 10, 3)  # time indices ahead: 0, 3, 6, 9


def time_to_collision(
    states: FloatArray,
    points: FloatArray,
    bounds: FloatArray,
    areas: npt.NDArray[np.bool_],
    row_token: IntArray,
    observations: ObservationBatch,
    maps: MapBatch,
    stopped_speed_threshold: float,
    step_s: float,
    evaluated_steps: Sequence[int],
) -> list[tuple[FloatArray, FirstInfraction]]:
    """Return TTC (R,) and each row's first infraction, time index and object (-1 if none), checking the first
    n time indices, for each n of `evaluated_steps`, from the states (R, T, 11), their box points (R, T, 5, 2),
    bounds (R, T, 4) and ego areas (R, T, 3).

    The contacts are found once, over the longest horizon; a shorter one keeps those that start before its
    end. That is what it finds alone: each contact is judged on its own, and whether it counts depends on the
    earlier contacts of its (row, object) only (`counted_contacts`).
    """
    num_rows = states.shape[0]
    num_steps = min(max(evaluated_steps), states.shape[1])
    num_projections = len(PROJECTION_STEPS)
    speed = np.hypot(states[..., StateIndex.VELOCITY_X], states[..., StateIndex.VELOCITY_Y])
    # A contact of a state slower than the threshold is dropped below, unjudged, as the devkit skips the state.
    # Each box's contacts are found on its own, so the rows slower throughout (stopped proposals) are left out
    # of the search: the other rows' contacts, and their order, are the same.
    searched = np.flatnonzero((speed[:, :num_steps] >= stopped_speed_threshold).any(axis=1))
    if not len(searched):
        return [no_contacts(num_rows) for _ in evaluated_steps]
    heading = states[searched, :num_steps, StateIndex.HEADING]
    searched_speed = speed[searched, :num_steps]
    # Along the heading with |v|: a reversing ego is projected forward, as in the devkit.
    velocity = np.stack([np.cos(heading) * searched_speed, np.sin(heading) * searched_speed], axis=-1)
    delta_t = PROJECTION_STEPS.astype(np.float64) * step_s
    shift = velocity[:, :, None, :] * delta_t[:, None]  # (searched rows, T, projection, 2)
    # Each box's 4 corners as 8 values (x, y, x, y, ...), each moved by the shift's x or y: numpy adds along a
    # last axis of 8 far faster than along one of 2.
    corners = ego_corners(points[searched, :num_steps]).reshape(len(searched), -1, 1, 8) + np.tile(shift, 4)
    # Every corner moves by the same shift and rounding is monotone, so the moved box's bounds are its bounds
    # moved, to the bit.
    box_bounds = bounds[searched, :num_steps, None] + np.tile(shift, 2)
    # Box s = k * 4 + projection: the devkit's visiting order, tested against map k + 0, 3, 6 or 9.
    map_index = (np.arange(num_steps)[:, None] + PROJECTION_STEPS).reshape(-1)
    contacts = find_contacts(
        corners.reshape(len(searched), -1, 4, 2),
        box_bounds.reshape(len(searched), -1, 4),
        map_index,
        row_token[searched],
        observations,
    )
    if not len(contacts.row):
        return [no_contacts(num_rows) for _ in evaluated_steps]
    row, step = searched[contacts.row], contacts.step // num_projections
    moving = speed[row, step] >= stopped_speed_threshold
    row, step, order, obj = row[moving], step[moving], contacts.step[moving], contacts.obj[moving]
    state = states[row, step]

    ahead, behind = contact_sides(state[:, : StateIndex.HEADING + 1], centroids(contacts.polygons[moving]))
    rear_axle_in_intersection = in_intersection(
        state[:, StateIndex.X], state[:, StateIndex.Y], row_token[row], maps
    )
    ego_area = areas[row, step]
    exposed = (
        ego_area[:, EgoArea.MULTIPLE_LANES]
        | ego_area[:, EgoArea.NON_DRIVABLE_AREA]
        | rear_axle_in_intersection
    )
    at_fault = ahead | (exposed & ~behind)

    results: list[tuple[FloatArray, FirstInfraction]] = []
    for horizon in evaluated_steps:
        kept = step < horizon
        counted = counted_contacts(row[kept], obj[kept], order[kept], at_fault[kept])
        scores = np.ones(num_rows)
        scores[row[kept][counted]] = 0.0
        results.append((scores, first_infraction(row[kept], step[kept], obj[kept], counted, num_rows)))
    return results
