"""Drivable-area compliance (DAC) in {0, 1}, a multiplier (docs/engine.md, "Metrics")."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from scorer.geometry import FloatArray
from scorer.metrics.ego_areas import EgoArea


def drivable_area_compliance(areas: npt.NDArray[np.bool_]) -> FloatArray:
    """Return DAC (P,): 0 when any corner leaves the drivable area at any of the 41 states, index 0 included."""
    return np.where(areas[..., EgoArea.NON_DRIVABLE_AREA].any(axis=-1), 0.0, 1.0)
