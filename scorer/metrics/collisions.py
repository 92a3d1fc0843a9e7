"""No at-fault collisions (NC), a multiplier in {0, 0.5, 1} (docs/engine.md, "Metrics").

Each contact at time index k (0..40, the initial state included) is classified as nuPlan's
`get_collision_type` does, in this order: stopped ego, stopped track (any static object, or an agent
whose first-appearance speed is at most 0.05 m/s), active rear (object behind), active front (the
front bumper touches it), active lateral. Stopped-track and front collisions are at fault, lateral
ones only while the ego straddles lanes or leaves the drivable area.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from scorer.geometry import FloatArray, IntArray
from scorer.metrics.contacts import (
    FirstInfraction,
    centroids,
    contact_sides,
    counted_contacts,
    find_contacts,
    first_infraction,
    no_contacts,
    segments_meet,
)
from scorer.metrics.ego_areas import EgoArea
from scorer.metrics.ego_box import BoxPoint, ego_corners
from scorer.observation import ObservationBatch
from scorer.trajectory import StateIndex

STOPPED_SPEED = 5e-2  # m/s, `get_collision_type` and `is_track_stopped` defaults (not the TTC threshold)
AGENT_COLLISION = 0.0  # vehicles, pedestrians, bicycles
OBJECT_COLLISION = 0.5  # static objects


def no_at_fault_collisions(
    states: FloatArray,
    points: FloatArray,
    bounds: FloatArray,
    areas: npt.NDArray[np.bool_],
    row_token: IntArray,
    observations: ObservationBatch,
) -> tuple[FloatArray, FirstInfraction]:
    """Return NC (R,) and each row's first at-fault collision: time index and object (-1 if none), from the
    states (R, T, 11), their box points (R, T, 5, 2), bounds (R, T, 4) and ego areas (R, T, 3)."""
    num_rows, num_steps = states.shape[:2]
    stopped = (
        np.hypot(states[..., StateIndex.VELOCITY_X], states[..., StateIndex.VELOCITY_Y]) <= STOPPED_SPEED
    )
    # A stopped ego is never at fault, and a contact it makes ignores its object only for that row: the rows
    # stopped throughout (stopped proposals) score 1 with no infraction whatever they touch, and are left out
    # of the search, which finds each box's contacts on its own.
    searched = np.flatnonzero(~stopped.all(axis=1))
    if not len(searched):
        return no_contacts(num_rows)
    contacts = find_contacts(
        ego_corners(points[searched]),
        bounds[searched],
        np.arange(num_steps),
        row_token[searched],
        observations,
    )
    if not len(contacts.row):
        return no_contacts(num_rows)
    row, step, obj = searched[contacts.row], contacts.step, contacts.obj
    state = states[row, step]

    ego_stopped = stopped[row, step]
    # nuPlan's `is_track_stopped`: anything that is not an Agent counts as stopped.
    track_stopped = ~observations.is_agent[obj] | (observations.first_speed[obj] <= STOPPED_SPEED)
    # The devkit asks for the angle only when neither is stopped.
    behind = np.zeros(len(row), dtype=bool)
    moving = ~ego_stopped & ~track_stopped
    behind[moving] = contact_sides(
        state[moving, : StateIndex.HEADING + 1], centroids(contacts.polygons[moving])
    )[1]
    ego = points[row, step]
    front = segments_meet(
        ego[:, BoxPoint.FRONT_LEFT], ego[:, BoxPoint.FRONT_RIGHT], ego_corners(ego), contacts
    )
    ego_area = areas[row, step]
    lateral_at_fault = ego_area[:, EgoArea.MULTIPLE_LANES] | ego_area[:, EgoArea.NON_DRIVABLE_AREA]
    at_fault = ~ego_stopped & (track_stopped | (~behind & (front | lateral_at_fault)))

    counted = counted_contacts(row, obj, step, at_fault)
    # The devkit scores by type (nuPlan's AGENT_TYPES); in its observations that is exactly the agents.
    severity = np.where(observations.is_agent[obj], AGENT_COLLISION, OBJECT_COLLISION)
    scores = np.ones(num_rows)
    np.minimum.at(scores, row[counted], severity[counted])
    return scores, first_infraction(row, step, obj, counted, num_rows)
