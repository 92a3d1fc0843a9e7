"""The ego's box as the scorer sees it: 4 corners and the centre per state.

See docs/engine.md, "Conventions: the ego vehicle and its box" and "Conventions: state arrays".
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

from scorer.geometry import EGO_HALF_LENGTH, EGO_HALF_WIDTH, FloatArray, IntArray, box_corners, ego_center
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


def repeated_from(values: FloatArray) -> IntArray:
    """Return, per row and step of `values` (R, T, ...), the first step of the run of steps whose values repeat
    each other to the bit (the step itself where it starts one): a proposal standing still repeats its boxes.

    A measure that reads a step's values alone takes a repeat's from that step (`measure[rows, repeated_from]`),
    and needs only the steps that start a run.
    """
    num_rows, num_steps = values.shape[:2]
    bits = np.ascontiguousarray(values).reshape(num_rows, num_steps, -1).view(np.uint64)
    starts = np.ones((num_rows, num_steps), dtype=bool)
    starts[:, 1:] = (bits[:, 1:] != bits[:, :-1]).any(axis=-1)
    return np.maximum.accumulate(np.where(starts, np.arange(num_steps), 0), axis=1)
