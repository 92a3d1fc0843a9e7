"""The IDM vehicles at the start: each current vehicle on its starting lane or connector, snapped to its
baseline, or the reason it is not simulated (docs/engine.md, "Reactive traffic: building the agents").

As NAVSIM's `NavsimIDMAgentsBuilder` on nuPlan's `get_starting_segment`, vehicle by vehicle in scene order:
* the starting segment: the lanes whose polygon contains the box centre strictly, else, inside an
  intersection, the lane connectors whose polygon contains it; of these (map-layer order) the first with the
  smallest |heading of the nearest baseline pose - box heading|, the difference **not** wrapped. The nearest
  pose is nuPlan's `get_nearest_pose_from_position`: shapely's `project` and `interpolate`, the heading
  Python's `math.atan2` towards the point 0.5 m further (or from 0.5 m back at the end);
* snapped to that pose when the centre lies within the snap threshold of it (numpy's `hypot`), else rejected;
* rejected when the snapped box touches (`intersects`) the ego's true initial box or the snapped box of an
  earlier accepted vehicle;
* speed = numpy's `hypot` of the recorded velocity, target velocity the segment's speed limit or, without
  one, the value the previous vehicle left in the builder's variable (initially the configured 10 m/s).

Vehicles that are not simulated may stay at their recorded pose as open-loop "parked" vehicles; whether one
can is decided here (standing, |v| < 0.1 m/s, outside every lane and intersection; or too far from its
baseline to snap), whether it does at a step depends on the simulated vehicles (`scorer.reactive.traffic`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

from scorer.geometry import CORNER_SIGNS
from scorer.reactive import geos
from scorer.reactive.paths import LanePath
from scorer.scene import Frame, Lane, MapExcerpt
from scorer.versions import IdmTraffic

VEHICLE = "vehicle"
PARKED_SPEED = 0.1  # m/s: below it a vehicle outside the lanes counts as parked
NEAREST_POSE_STEP = 0.5  # m along the baseline towards which the nearest pose's heading points
TRIGONOMETRY_MEMO = 4096  # headings whose box trigonometry is kept (`box_trigonometry`)
_TRIGONOMETRY: dict[float, tuple[float, float, float, float]] = {}


@dataclass(frozen=True, eq=False)
class IdmVehicle:
    """A simulated vehicle at the start: its recorded object, segment, path and IDM state."""

    track: str
    segment: str  # the id of its starting lane or lane connector
    segment_layer: str  # "LANE" or "LANE_CONNECTOR"
    path: LanePath
    progress: float  # m along the path (= along the baseline)
    speed: float  # m/s
    target_velocity: float  # m/s
    lateral_deviation: float  # m from the recorded centre to the baseline
    length: float
    width: float
    pose: tuple[float, float, float]  # the snapped box centre x, y, heading


@dataclass(frozen=True)
class Rejection:
    """Why a current vehicle is not simulated."""

    reason: str  # "no_starting_segment", "lateral_deviation" or "collision_at_start"
    lateral_deviation: float | None = None
    segment: str | None = None


@dataclass(frozen=True)
class ParkingCandidate:
    """A vehicle that is not simulated but may stay at its recorded box (x, y, heading, length, width)."""

    track: str
    box: tuple[float, float, float, float, float]


@dataclass(frozen=True, eq=False)
class StartingTraffic:
    """The current frame's vehicles at the start of a reactive simulation."""

    agents: tuple[IdmVehicle, ...]
    rejected: dict[str, Rejection]
    parking: tuple[ParkingCandidate, ...]  # scene order
    # Why the devkit's builder fails the token (a NaN velocity, a baseline too short for a path): every
    # trajectory of the scene is then unscorable, as the official row is invalid.
    failure: str | None = None


@dataclass(frozen=True)
class _Segment:
    lane: Lane
    layer: str
    progress: float
    pose: tuple[float, float, float]


def _nearest_pose(
    baseline: shapely.LineString, x: float, y: float
) -> tuple[float, tuple[float, float, float]]:
    """Return the progress of the point of `baseline` nearest (x, y), and that point with the baseline heading."""
    progress = float(shapely.line_locate_point(baseline, shapely.Point(x, y)))
    point = shapely.line_interpolate_point(baseline, progress)
    ahead = shapely.line_interpolate_point(baseline, progress + NEAREST_POSE_STEP)
    if point.x == ahead.x and point.y == ahead.y:
        behind = shapely.line_interpolate_point(baseline, progress - NEAREST_POSE_STEP)
        heading = math.atan2(point.y - behind.y, point.x - behind.x)
    else:
        heading = math.atan2(ahead.y - point.y, ahead.x - point.x)
    return progress, (point.x, point.y, heading)


def starting_segment(map_excerpt: MapExcerpt, x: float, y: float, heading: float) -> _Segment | None:
    """Return the starting lane or connector of a box centred at (x, y) with `heading`, or None."""
    lanes, layer = map_excerpt.lanes, "LANE"
    inside = shapely.contains_xy([lane.polygon for lane in lanes], x, y) if lanes else np.zeros(0, bool)
    if not inside.any():
        areas = [area.polygon for area in map_excerpt.intersections]
        if not (areas and shapely.contains_xy(areas, x, y).any()):
            return None
        lanes, layer = map_excerpt.lane_connectors, "LANE_CONNECTOR"
        inside = shapely.contains_xy([lane.polygon for lane in lanes], x, y) if lanes else np.zeros(0, bool)
    candidates = [lanes[index] for index in np.flatnonzero(inside)]
    if not candidates:
        return None
    nearest = [_nearest_pose(shapely.LineString(lane.baseline), x, y) for lane in candidates]
    chosen = int(np.argmin(np.abs([pose[2] - heading for _, pose in nearest])))
    return _Segment(candidates[chosen], layer, *nearest[chosen])


def _in_lane_or_intersection(map_excerpt: MapExcerpt, x: float, y: float) -> bool:
    polygons = [lane.polygon for lane in map_excerpt.lanes] + [
        area.polygon for area in map_excerpt.intersections
    ]
    return bool(polygons) and bool(shapely.contains_xy(polygons, x, y).any())


def box_polygon(x: float, y: float, heading: float, length: float, width: float) -> shapely.Polygon:
    """Return the box polygon nuPlan's `OrientedBox.geometry` gives (PDM's corner formula, FL, RL, RR, FR).

    The corners of `box_corners` for one box, without numpy's per-call cost where it adds nothing: the
    sines and cosines from the numpy functions it calls (`box_trigonometry`), the products and sums in
    Python floats (the same operations in the same order, rounded alike)."""
    lat_cos, lon_cos, lat_sin, lon_sin = box_trigonometry(heading)
    half_length, half_width = length / 2.0, width / 2.0
    corners = []
    for lon_sign, lat_sign in CORNER_SIGNS:
        lon, lat = lon_sign * half_length, lat_sign * half_width
        corners.append((x + (lat * lat_cos + lon * lon_cos), y + (lat * lat_sin + lon * lon_sin)))
    return geos.polygon(corners)


def box_trigonometry(heading: float) -> tuple[float, float, float, float]:
    """Return cos(heading + pi / 2), cos(heading), sin(heading + pi / 2) and sin(heading), from numpy's
    `cos` and `sin` of the angles `box_corners` computes (numpy's sum, as Python's, is the rounded sum),
    memoised: a vehicle keeps its heading along a straight stretch of its path, step after step (not a zero
    heading: 0.0 and -0.0 are one key, and their sines differ in sign)."""
    trigonometry = _TRIGONOMETRY.get(heading) if heading else None
    if trigonometry is None:
        if len(_TRIGONOMETRY) >= TRIGONOMETRY_MEMO:
            _TRIGONOMETRY.clear()
        angles = np.array([heading + math.pi / 2, heading])
        (lat_cos, lon_cos), (lat_sin, lon_sin) = np.cos(angles).tolist(), np.sin(angles).tolist()
        trigonometry = lat_cos, lon_cos, lat_sin, lon_sin
        if heading:
            _TRIGONOMETRY[heading] = trigonometry
    return trigonometry


def build_agents(
    frame: Frame, map_excerpt: MapExcerpt, ego_box: shapely.Polygon, config: IdmTraffic
) -> StartingTraffic:
    """Return the IDM vehicles of the current `frame`, the rejected ones and the parking candidates; `ego_box`
    is the ego's true initial box. Where the devkit's builder fails, no vehicles and the failure."""
    try:
        return _build_agents(frame, map_excerpt, ego_box, config)
    except ValueError as error:
        return StartingTraffic(agents=(), rejected={}, parking=(), failure=str(error))


def _build_agents(
    frame: Frame, map_excerpt: MapExcerpt, ego_box: shapely.Polygon, config: IdmTraffic
) -> StartingTraffic:
    agents: list[IdmVehicle] = []
    rejected: dict[str, Rejection] = {}
    parking: list[ParkingCandidate] = []
    occupied = [ego_box]
    target_velocity = config.target_velocity
    for row, (track, category) in enumerate(zip(frame.tracks, frame.categories, strict=True)):
        if category != VEHICLE:
            continue
        x, y, _, length, width, _, heading = frame.boxes[row].tolist()
        recorded = ParkingCandidate(track, (x, y, heading, length, width))
        velocity_x, velocity_y = frame.velocities[row].tolist()
        recorded_speed = float(np.hypot(velocity_x, velocity_y))
        segment = starting_segment(map_excerpt, x, y, heading)
        if segment is None:
            rejected[track] = Rejection("no_starting_segment")
            if recorded_speed < PARKED_SPEED and not _in_lane_or_intersection(map_excerpt, x, y):
                parking.append(recorded)
            continue
        deviation = float(np.hypot(segment.pose[0] - x, segment.pose[1] - y))
        if deviation > config.idm_snap_threshold:
            rejected[track] = Rejection("lateral_deviation", deviation, segment.lane.id)
            parking.append(recorded)
            continue
        snapped = box_polygon(*segment.pose, length, width)
        if shapely.intersects(occupied, snapped).any():
            rejected[track] = Rejection("collision_at_start", deviation, segment.lane.id)
            continue
        occupied.append(snapped)
        if math.isnan(recorded_speed):
            raise ValueError(f"vehicle {track} has no velocity")
        target_velocity = segment.lane.speed_limit_mps or target_velocity
        agents.append(
            IdmVehicle(
                track=track,
                segment=segment.lane.id,
                segment_layer=segment.layer,
                path=LanePath.of_baseline(segment.lane.baseline),
                progress=segment.progress,
                speed=recorded_speed,
                target_velocity=target_velocity,
                lateral_deviation=deviation,
                length=length,
                width=width,
                pose=segment.pose,
            )
        )
    return StartingTraffic(agents=tuple(agents), rejected=rejected, parking=tuple(parking))
