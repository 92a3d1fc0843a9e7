"""The ego's box as the scorer sees it: 4 corners and the centre per state.

See docs/engine.md, "Conventions: the ego vehicle and its box" and "Conventions: state arrays".
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

from scorer.geometry import EGO_HALF_LENGTH, EGO_HALF_WIDTH, FloatArray, box_corners, ego_center
from scorer.trajectory import StateIndex


class BoxPoint(IntEnum):
    """Points of a box array (PDM's `BBCoordsIndex`): the ring order FL, RL, RR, FR, then the centre."""

    FRONT_LEFT = 0
    REAR_LEFT = 1
    REAR_RIGHT = 2
    FRONT_RIGHT = 3
    CENTER = 4


def ego_box_points(states: FloatArray) -> FloatArray:
    """Return the ego box points (..., 5, 2) of rear-axle states (..., 11) (`state_array_to_coords_array`)."""
    heading = states[..., StateIndex.HEADING]
    center = np.stack(ego_center(states[..., StateIndex.X], states[..., StateIndex.Y], heading), axis=-1)
    corners = box_corners(center[..., 0], center[..., 1], heading, EGO_HALF_LENGTH, EGO_HALF_WIDTH)
    return np.concatenate([corners, center[..., None, :]], axis=-2)


def ego_corners(points: FloatArray) -> FloatArray:
    """Return the 4 corners (..., 4, 2) of box points (..., 5, 2): the devkit's polygon ring FL, RL, RR, FR."""
    return points[..., : BoxPoint.CENTER, :]
