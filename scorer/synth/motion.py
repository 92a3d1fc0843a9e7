"""Motion over the 14 frames of a synthetic scene: smooth speed and lateral profiles, tracks, the ego, and
the check that keeps boxes from overlapping."""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
import numpy.typing as npt

from scorer.geometry import (
    EGO_LENGTH,
    EGO_WIDTH,
    BoolArray,
    FloatArray,
    arctan2_avx512,
    box_corners,
    ego_center,
)
from scorer.synth.polyline import Polyline

FRAME_COUNT = 14
CURRENT_INDEX = 3
FRAME_INTERVAL_S = 0.5
FRAME_TIMES = (np.arange(FRAME_COUNT) - CURRENT_INDEX) * FRAME_INTERVAL_S


def smoothstep(u: npt.ArrayLike) -> FloatArray:
    """Return 3u^2 - 2u^3 on [0, 1], 0 before and 1 after."""
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


@dataclass(frozen=True)
class Transition:
    """A value going smoothly (smoothstep) from `start` to `end` over [t1, t2], constant before and after."""

    start: float
    end: float
    t1: float = 0.0
    t2: float = 1.0

    @classmethod
    def constant(cls, value: float) -> Transition:
        """Return a value that never changes."""
        return cls(value, value)

    def _phase(self, t: npt.ArrayLike) -> FloatArray:
        return (np.asarray(t, dtype=np.float64) - self.t1) / (self.t2 - self.t1)

    def value(self, t: npt.ArrayLike) -> FloatArray:
        """Return the value at times t."""
        return self.start + (self.end - self.start) * smoothstep(self._phase(t))

    def rate(self, t: npt.ArrayLike) -> FloatArray:
        """Return the time derivative at times t."""
        u = np.clip(self._phase(t), 0.0, 1.0)
        return (self.end - self.start) * 6.0 * u * (1.0 - u) / (self.t2 - self.t1)

    def integral(self, t: npt.ArrayLike) -> FloatArray:
        """Return the integral of the value from time 0 to t (the distance of a speed profile)."""

        def antiderivative(times: FloatArray) -> FloatArray:
            u = self._phase(times)
            inside = np.clip(u, 0.0, 1.0)
            ramp = np.where(u >= 1.0, u - 0.5, inside**3 - 0.5 * inside**4)
            return self.start * times + (self.end - self.start) * (self.t2 - self.t1) * ramp

        return antiderivative(np.asarray(t, dtype=np.float64)) - antiderivative(np.zeros(1))[0]

    def distance_until_settled(self) -> float:
        """Return the distance covered from time 0 until the end of the transition (t2 >= 0): a stop's distance."""
        return float(self.integral(self.t2))


def braking(speed: float, deceleration: float, delay: float = 0.0) -> Transition:
    """Return a smooth stop from `speed` starting after `delay` s, peaking at `deceleration` (m/s^2)."""
    if speed <= 0.0:
        return Transition.constant(0.0)
    # A smoothstep from v to 0 over d seconds peaks at 1.5 v / d.
    return Transition(speed, 0.0, delay, delay + 1.5 * speed / deceleration)


@dataclass(frozen=True, eq=False)
class Track:
    """An object over the frames; `seen` marks the frames it is annotated in."""

    category: str
    size: tuple[float, float, float]  # length, width, height
    poses: FloatArray  # (FRAME_COUNT, 3) box centre x, y, heading
    velocity: FloatArray  # (FRAME_COUNT, 2) global frame
    seen: BoolArray

    def with_seen(self, seen: BoolArray) -> Track:
        """Return the same track annotated in other frames."""
        return Track(self.category, self.size, self.poses, self.velocity, seen)


def drive(
    path: Polyline, s0: float, speed: Transition, lateral: Transition | None = None
) -> tuple[FloatArray, FloatArray]:
    """Return poses (FRAME_COUNT, 3) and global velocities along `path` from arc length s0 at t = 0."""
    lateral = lateral or Transition.constant(0.0)
    s = s0 + speed.integral(FRAME_TIMES)
    poses = path.poses(s, lateral.value(FRAME_TIMES))
    along = speed.value(FRAME_TIMES)
    across = lateral.rate(FRAME_TIMES)
    path_heading = poses[:, 2].copy()
    poses[:, 2] = path_heading + arctan2_avx512(across, np.maximum(along, 0.5))
    cos_h, sin_h = np.cos(path_heading), np.sin(path_heading)
    velocity = np.stack([along * cos_h - across * sin_h, along * sin_h + across * cos_h], axis=-1)
    return poses, velocity


def moving_track(
    category: str,
    size: tuple[float, float, float],
    path: Polyline,
    s0: float,
    speed: Transition,
    lateral: Transition | None = None,
) -> Track:
    """Return an agent driving (walking, riding) along `path`."""
    poses, velocity = drive(path, s0, speed, lateral)
    return Track(category, size, poses, velocity, np.ones(FRAME_COUNT, dtype=bool))


def static_track(
    category: str, size: tuple[float, float, float], x: float, y: float, heading: float
) -> Track:
    """Return an object standing still at one pose."""
    poses = np.tile([x, y, heading], (FRAME_COUNT, 1))
    return Track(category, size, poses, np.zeros((FRAME_COUNT, 2)), np.ones(FRAME_COUNT, dtype=bool))


@dataclass(frozen=True, eq=False)
class EgoMotion:
    """The recorded ego: rear-axle poses and dynamics (ego frame) at every frame."""

    poses: FloatArray  # (FRAME_COUNT, 3)
    speed: FloatArray
    acceleration: FloatArray
    lateral_acceleration: FloatArray

    def boxes(self) -> FloatArray:
        """Return the ego boxes (FRAME_COUNT, 5): centre x, y, heading, length, width."""
        x, y = ego_center(self.poses[:, 0], self.poses[:, 1], self.poses[:, 2])
        return np.stack(
            [x, y, self.poses[:, 2], np.full(FRAME_COUNT, EGO_LENGTH), np.full(FRAME_COUNT, EGO_WIDTH)], -1
        )


def ego_motion(path: Polyline, s0: float, speed: Transition, lateral: Transition | None = None) -> EgoMotion:
    """Return the ego driving along `path` (its rear axle on the path) from arc length s0 at t = 0."""
    poses, _ = drive(path, s0, speed, lateral)
    along = speed.value(FRAME_TIMES)
    curvature = path.curvature(s0 + speed.integral(FRAME_TIMES))
    return EgoMotion(poses, along, speed.rate(FRAME_TIMES), along * along * curvature)


def track_boxes(tracks: list[Track]) -> FloatArray:
    """Return boxes (n, FRAME_COUNT, 5); a track annotated once stands at that pose in every frame (as the engine reads it)."""
    boxes = np.empty((len(tracks), FRAME_COUNT, 5))
    for index, track in enumerate(tracks):
        poses = track.poses
        if track.seen.sum() == 1:
            poses = np.repeat(poses[track.seen], FRAME_COUNT, axis=0)
        boxes[index, :, :3] = poses
        boxes[index, :, 3:] = track.size[:2]
    return boxes


def boxes_overlap(a: FloatArray, b: FloatArray, margin: float = 0.0) -> BoolArray:
    """Return whether boxes (..., 5) overlap (separating-axis test), each grown by `margin` on every side."""
    corners_a = box_corners(a[..., 0], a[..., 1], a[..., 2], a[..., 3] / 2 + margin, a[..., 4] / 2 + margin)
    corners_b = box_corners(b[..., 0], b[..., 1], b[..., 2], b[..., 3] / 2 + margin, b[..., 4] / 2 + margin)
    headings = np.stack(
        np.broadcast_arrays(a[..., 2], a[..., 2] + np.pi / 2, b[..., 2], b[..., 2] + np.pi / 2), -1
    )
    axis_x, axis_y = np.cos(headings)[..., None], np.sin(headings)[..., None]  # (..., 4 axes, 1)
    project_a = (
        axis_x * corners_a[..., None, :, 0] + axis_y * corners_a[..., None, :, 1]
    )  # (..., 4 axes, 4 corners)
    project_b = axis_x * corners_b[..., None, :, 0] + axis_y * corners_b[..., None, :, 1]
    separated = (project_a.max(-1) < project_b.min(-1)) | (project_b.max(-1) < project_a.min(-1))
    return ~separated.any(-1)


def _may_touch(a: FloatArray, b: FloatArray, margin: float) -> BoolArray:
    """Return whether the bounding circles of boxes (..., 5) come within `margin` (a cheap pre-test)."""
    reach = 0.5 * (np.hypot(a[..., 3], a[..., 4]) + np.hypot(b[..., 3], b[..., 4])) + 2 * margin
    return np.hypot(a[..., 0] - b[..., 0], a[..., 1] - b[..., 1]) <= reach


def overlaps_ego(ego: EgoMotion, track: Track, margin: float) -> bool:
    """Return whether the track's box comes within `margin` of the ego's in any frame."""
    return bool(boxes_overlap(track_boxes([track])[0], ego.boxes(), margin).any())


def drop_conflicts(ego: EgoMotion, tracks: list[Track], ego_margin: float, pair_margin: float) -> list[Track]:
    """Return the tracks that never overlap the ego nor an earlier kept track, in any frame (earlier tracks win)."""
    if not tracks:
        return []
    boxes = track_boxes(tracks)
    hits_ego = cast(BoolArray, boxes_overlap(boxes, ego.boxes()[None], ego_margin).any(axis=1))
    first, second = np.triu_indices(len(tracks), k=1)
    near = _may_touch(boxes[first], boxes[second], pair_margin).any(axis=1)
    first, second = first[near], second[near]
    hits = boxes_overlap(boxes[first], boxes[second], pair_margin).any(axis=1)
    conflicts = np.zeros((len(tracks), len(tracks)), dtype=bool)
    conflicts[second[hits], first[hits]] = True
    kept: list[int] = []
    for index in range(len(tracks)):
        if not hits_ego[index] and not conflicts[index, kept].any():
            kept.append(index)
    return [tracks[index] for index in kept]


def limit_sight(ego: EgoMotion, tracks: list[Track], sight_range: float) -> list[Track]:
    """Return the tracks annotated only in frames where they are within `sight_range` of the ego (never-seen ones dropped)."""
    result = []
    for track in tracks:
        near = np.hypot(*(track.poses[:, :2] - ego.poses[:, :2]).T) <= sight_range
        seen = track.seen & near
        if seen.any():
            result.append(track.with_seen(seen))
    return result
