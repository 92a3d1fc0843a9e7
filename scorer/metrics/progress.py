"""Ego progress (EP): raw progress along the centerline and its normalisation (docs/engine.md, "Metrics")."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import shapely

from scorer.geometry import FloatArray, IntArray
from scorer.metrics.ego_box import BoxPoint
from scorer.versions import ProgressNormalisation


def centerline_strings(centerlines: list[FloatArray]) -> npt.NDArray[np.object_]:
    """Return one LineString (B,) per centerline (n, >=2) x, y vertices."""
    vertices = np.concatenate([np.asarray(line, dtype=np.float64)[:, :2] for line in centerlines])
    owner = np.repeat(np.arange(len(centerlines)), [len(line) for line in centerlines])
    return np.asarray(shapely.linestrings(vertices, indices=owner), dtype=object).reshape(len(centerlines))


def raw_progress(points: FloatArray, centerlines: npt.NDArray[np.object_], row_token: IntArray) -> FloatArray:
    """Return max(0, progress of the last centre - progress of the first) along each row's centerline (R,)."""
    ends = points[:, [0, -1], BoxPoint.CENTER]
    with np.errstate(invalid="ignore"):
        located = shapely.line_locate_point(centerlines[row_token][:, None], shapely.points(ends))
    return np.clip(located[:, 1] - located[:, 0], 0.0, None)


def normalised_progress(
    raw: FloatArray, multiplier: FloatArray, threshold: float, normalisation: ProgressNormalisation
) -> FloatArray:
    """Return EP (B, P) relative to the best multiplier-scaled progress of each token's proposals.

    "masked" (v1): scaled progress / best; when no scaled progress exceeds `threshold`, 1 where the
    multiplier is non-zero, else 0. "clipped" (v2): raw progress / best clipped to [0, 1]; all ones when
    no scaled progress exceeds `threshold`. v2 never zeroes EP for a failed multiplier.
    """
    scaled = raw * multiplier
    best = np.max(scaled, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        if normalisation == "clipped":
            return np.where(best > threshold, np.clip(raw / best, 0.0, 1.0), 1.0)
        relative = scaled / best
    return np.where(best > threshold, relative, np.where(multiplier == 0.0, 0.0, 1.0))
