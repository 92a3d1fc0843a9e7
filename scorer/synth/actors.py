"""Objects of synthetic scenes: realistic box sizes and placements shared by every scene kind."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from scorer.geometry import EGO_FRONT_LENGTH, FloatArray
from scorer.synth.motion import (
    CURRENT_INDEX,
    FRAME_COUNT,
    FRAME_TIMES,
    EgoMotion,
    Track,
    Transition,
    moving_track,
    overlaps_ego,
    static_track,
)
from scorer.synth.polyline import Polyline

# (length, width, height) ranges in metres.
SIZE_RANGES: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "car": ((4.3, 5.3), (1.78, 2.1), (1.4, 1.9)),
    "truck": ((8.0, 12.5), (2.35, 2.6), (2.9, 3.6)),
    "pedestrian": ((0.55, 0.9), (0.5, 0.8), (1.5, 1.9)),
    "bicycle": ((1.6, 1.9), (0.55, 0.8), (1.5, 1.8)),
    "traffic_cone": ((0.3, 0.5), (0.3, 0.5), (0.5, 0.9)),
    "barrier": ((1.0, 2.5), (0.3, 0.6), (0.8, 1.1)),
    "czone_sign": ((0.5, 0.9), (0.15, 0.4), (1.4, 2.2)),
    "generic_object": ((0.4, 1.2), (0.4, 1.2), (0.3, 1.2)),
}
TRUCK_SHARE = 0.1
PEDESTRIAN_CLEARANCE = 0.4  # m a crossing pedestrian keeps from the recorded ego


def object_size(rng: np.random.Generator, kind: str) -> tuple[float, float, float]:
    """Return a (length, width, height) drawn for a kind of SIZE_RANGES, to the millimetre."""
    return tuple(round(float(rng.uniform(low, high)), 3) for low, high in SIZE_RANGES[kind])  # type: ignore[return-value]


def vehicle_size(rng: np.random.Generator) -> tuple[float, float, float]:
    """Return the size of a car, or now and then of a truck or bus."""
    return object_size(rng, "truck" if rng.random() < TRUCK_SHARE else "car")


def vehicle(
    rng: np.random.Generator, path: Polyline, s0: float, speed: Transition, lateral: Transition | None = None
) -> Track:
    """Return a vehicle driving along `path` (its box centre on the path)."""
    return moving_track("vehicle", vehicle_size(rng), path, s0, speed, lateral)


def parked(
    rng: np.random.Generator, category: str, size_kind: str, pose: Sequence[float] | FloatArray
) -> Track:
    """Return a static object (or a vehicle standing still) at pose x, y, heading."""
    return static_track(category, object_size(rng, size_kind), float(pose[0]), float(pose[1]), float(pose[2]))


def gap_ahead(ego_s: FloatArray, lead_s: FloatArray, lead_length: float) -> float:
    """Return the smallest gap (m) over the frames from the ego's front bumper to a lead's rear, along one path."""
    return float(np.min(lead_s - 0.5 * lead_length - (ego_s + EGO_FRONT_LENGTH)))


def walker(
    rng: np.random.Generator, start: FloatArray, end: FloatArray, speed: float, t_start: float
) -> Track:
    """Return a pedestrian walking from `start` to `end` (straight), leaving at time t_start, then waiting there."""
    path = Polyline.from_points(np.stack([start, end]))
    distance = np.clip(speed * (FRAME_TIMES - t_start), 0.0, path.length)
    poses = path.poses(distance)
    walking = (FRAME_TIMES > t_start) & (distance < path.length)
    heading = poses[0, 2]
    velocity = np.where(walking[:, None], speed * np.array([np.cos(heading), np.sin(heading)]), 0.0)
    return Track(
        "pedestrian", object_size(rng, "pedestrian"), poses, velocity, np.ones(FRAME_COUNT, dtype=bool)
    )


def crossing_walker(
    rng: np.random.Generator, ego: EgoMotion, ends: FloatArray, tries: int = 4
) -> Track | None:
    """Return a pedestrian walking from ends[0] to ends[1], leaving at a time that keeps it clear of the ego (or None)."""
    for _ in range(tries):
        track = walker(rng, ends[0], ends[1], float(rng.uniform(1.1, 1.6)), float(rng.uniform(-6.0, 3.0)))
        if not overlaps_ego(ego, track, PEDESTRIAN_CLEARANCE):
            return track
    return None


def stroller(rng: np.random.Generator, line: FloatArray) -> Track:
    """Return a pedestrian walking along a walkway centre line, either way."""
    path = Polyline.from_points(line if rng.random() < 0.5 else line[::-1])
    speed = Transition.constant(float(rng.uniform(0.8, 1.6)))
    return moving_track(
        "pedestrian", object_size(rng, "pedestrian"), path, float(rng.uniform(5.0, path.length - 10.0)), speed
    )


def row_of_statics(
    rng: np.random.Generator,
    path: Polyline,
    s_start: float,
    count: int,
    spacing: float,
    lateral: float,
    kind: str,
) -> list[Track]:
    """Return `count` static objects of one kind along `path`, `spacing` apart, `lateral` to the left of it."""
    s = s_start + spacing * np.arange(count)
    poses = path.poses(s, lateral)
    return [parked(rng, kind, kind, pose) for pose in poses]


def seen_once(rng: np.random.Generator, track: Track) -> Track:
    """Return the track annotated in a single frame from the current one on (the engine holds it there for 5 s)."""
    seen = np.zeros(FRAME_COUNT, dtype=bool)
    seen[int(rng.integers(CURRENT_INDEX, FRAME_COUNT))] = True
    return track.with_seen(seen)


def seen_in_history_only(track: Track) -> Track:
    """Return the track annotated only before the current frame (it left the scene; the engine never sees it)."""
    return track.with_seen(np.arange(FRAME_COUNT) < CURRENT_INDEX)
