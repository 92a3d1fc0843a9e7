"""Densely sampled planar paths: road reference lines, lane centres and the paths agents drive along."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from scorer.geometry import FloatArray, IntArray, arctan2_avx512

GRID_STEP = 1.0  # m between vertices of reference lines and lane centres


@dataclass(frozen=True, eq=False)
class Polyline:
    """A path as vertices with unwrapped vertex headings and cumulative arc length."""

    points: FloatArray  # (n, 2)
    heading: FloatArray  # (n,) unwrapped; at a vertex, the mean of its two segments' headings
    arclength: FloatArray  # (n,)

    @classmethod
    def from_points(cls, vertices: npt.ArrayLike) -> Polyline:
        """Return the path through `vertices`, dropping repeated ones."""
        given: FloatArray = np.asarray(vertices, dtype=np.float64)
        keep = np.concatenate([[True], np.any(np.diff(given, axis=0) != 0.0, axis=1)])
        points = given[keep]
        segments = np.diff(points, axis=0)
        segment_heading = arctan2_avx512(segments[:, 1], segments[:, 0])
        turns = np.diff(segment_heading)
        # Unwrapped: every turn between segments taken in (-pi, pi].
        segment_heading[1:] = segment_heading[0] + np.cumsum(
            turns - 2 * np.pi * np.round(turns / (2 * np.pi))
        )
        heading = np.empty(len(points))
        heading[0], heading[-1] = segment_heading[0], segment_heading[-1]
        heading[1:-1] = 0.5 * (segment_heading[:-1] + segment_heading[1:])
        arclength = np.concatenate([[0.0], np.cumsum(np.hypot(segments[:, 0], segments[:, 1]))])
        return cls(points, heading, arclength)

    @property
    def length(self) -> float:
        """Return the path length."""
        return float(self.arclength[-1])

    def normals(self) -> FloatArray:
        """Return the unit left normals (n, 2) at the vertices."""
        return np.stack([-np.sin(self.heading), np.cos(self.heading)], axis=-1)

    def offset(self, lateral: float) -> FloatArray:
        """Return the vertices shifted `lateral` metres to the left (negative: right)."""
        return self.points + lateral * self.normals()

    def reversed(self) -> Polyline:
        """Return the same path driven the other way."""
        return Polyline(
            self.points[::-1].copy(), self.heading[::-1] + np.pi, self.length - self.arclength[::-1]
        )

    def curvature(self, s: npt.ArrayLike) -> FloatArray:
        """Return the path curvature (1/m, positive to the left) at arc lengths `s`."""
        kappa: FloatArray = np.gradient(self.heading, self.arclength)
        return np.interp(np.asarray(s, dtype=np.float64), self.arclength, kappa, left=0.0, right=0.0)

    def poses(self, s: npt.ArrayLike, lateral: npt.ArrayLike = 0.0) -> FloatArray:
        """Return poses (..., 3) x, y, heading at arc lengths `s`, shifted `lateral` to the left.

        Beyond either end the path continues straight along its end heading.
        """
        s = np.asarray(s, dtype=np.float64)
        clipped = np.clip(s, 0.0, self.length)
        heading = np.interp(clipped, self.arclength, self.heading)
        x = np.interp(clipped, self.arclength, self.points[:, 0]) + (s - clipped) * np.cos(heading)
        y = np.interp(clipped, self.arclength, self.points[:, 1]) + (s - clipped) * np.sin(heading)
        lateral = np.asarray(lateral, dtype=np.float64)
        x = x - lateral * np.sin(heading)
        y = y + lateral * np.cos(heading)
        return np.stack(np.broadcast_arrays(x, y, heading), axis=-1)


def road_line(start: Sequence[float] | FloatArray, heading: float, curvature: FloatArray) -> Polyline:
    """Return the reference line starting at `start` whose k-th GRID_STEP segment has curvature[k]."""
    segment_heading = heading + np.cumsum(curvature) * GRID_STEP - 0.5 * curvature * GRID_STEP
    steps = GRID_STEP * np.stack([np.cos(segment_heading), np.sin(segment_heading)], axis=-1)
    points = np.concatenate([np.asarray(start, dtype=np.float64)[None], start + np.cumsum(steps, axis=0)])
    return Polyline.from_points(points)


def curve_profile(n_steps: int, start: float, length: float, ramp: float, curvature: float) -> FloatArray:
    """Return per-step curvature: 0, ramping up (clothoid-like) to `curvature` over `ramp` m, held, ramping down."""
    s = (np.arange(n_steps) + 0.5) * GRID_STEP - start
    rising = np.clip(s / ramp, 0.0, 1.0)
    falling = np.clip((length - s) / ramp, 0.0, 1.0)
    return curvature * np.minimum(rising, falling) * (s > 0) * (s < length)


def bezier(p0: FloatArray, h0: float, p3: FloatArray, h3: float, tangent: float) -> FloatArray:
    """Return a cubic Bezier from p0 (leaving along h0) to p3 (arriving along h3), about GRID_STEP apart."""
    p1 = p0 + tangent * np.array([np.cos(h0), np.sin(h0)])
    p2 = p3 - tangent * np.array([np.cos(h3), np.sin(h3)])
    # Mean of chord and control-polygon length: close to the arc length of these gentle curves.
    control = np.stack([p0, p1, p2, p3])
    approx_length = 0.5 * (np.hypot(*(p3 - p0)) + np.hypot(*np.diff(control, axis=0).T).sum())
    t = np.linspace(0.0, 1.0, max(3, int(np.ceil(approx_length / GRID_STEP)) + 1))[:, None]
    u = 1.0 - t
    return u**3 * p0 + 3 * u * u * t * p1 + 3 * u * t * t * p2 + t**3 * p3


def concatenate(paths: Sequence[FloatArray]) -> Polyline:
    """Return the path through consecutive vertex arrays (shared end points appear once)."""
    return Polyline.from_points(np.concatenate(paths))


def sample_indices(n: int, stride: int) -> IntArray:
    """Return every `stride`-th index of n vertices, always including the last."""
    indices = np.arange(0, n, stride)
    return indices if indices[-1] == n - 1 else np.append(indices, n - 1)
