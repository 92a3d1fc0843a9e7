"""Corridor scenes: a two-way road, straight or curved, sometimes beside a car park.

Kinds: `straight`, `curve`, `carpark` (the ego drives past a car park) and `carpark_start` (the ego is
parked in it). The ego's plan comes first (its speed, a lead vehicle's behaviour, a lane change, a
pedestrian to yield to); the other road users are placed around it, and the export drops whatever
would touch the ego.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scorer.geometry import EGO_FRONT_LENGTH, EGO_REAR_LENGTH, REAR_AXLE_TO_CENTER, FloatArray
from scorer.synth.actors import (
    crossing_walker,
    object_size,
    parked,
    row_of_statics,
    stroller,
    vehicle,
    vehicle_size,
    walker,
)
from scorer.synth.draft import SPEED_LIMITS, Dice, SceneDraft, ego_initial_speed, lead_plan, vary_sightings
from scorer.synth.motion import (
    EgoMotion,
    Track,
    Transition,
    braking,
    ego_motion,
    moving_track,
)
from scorer.synth.polyline import Polyline, curve_profile, road_line, sample_indices
from scorer.synth.roadmap import BASELINE_STRIDE, Carriageway, RoadMap, cut_sections, ring, two_way_road

ROAD_VERTICES = 421  # a 420 m road on the 1 m grid
ROUTE_VARIANTS = {"normal": 0.55, "with_previous": 0.15, "starts_ahead": 0.15, "missing_connector": 0.15}
LEAD_BEHAVIOURS = {"none": 0.3, "cruise": 0.3, "brake": 0.2, "stopped": 0.2}
QUEUE_BEHAVIOURS = {"none": 0.5, "stopped": 0.5}
MAX_SPEED_BEHIND_STOPPED = 12.0  # m/s
# Lane changes are unhurried: the scorer's tracker follows 2 Hz poses with some lag and overshoots quick ones.
MIN_LANE_CHANGE_SPEED = 7.0  # m/s
LANE_CHANGE_DURATION = (4.0, 6.0)  # s
CURVE_LATERAL_ACCELERATION = 2.5  # m/s^2 at the ego's initial speed on the sharpest curve ahead


@dataclass(frozen=True)
class Carpark:
    """A car park right of the forward carriageway, touching its edge."""

    first: int  # reference vertices it spans
    last: int
    depth: float  # m from the road edge

    def spots(self, dice: Dice, road_edge: float) -> tuple[list[tuple[float, float, float]], float]:
        """Return two rows of parking spots (reference arc length, lateral offset, heading offset towards the
        aisle) and the lateral offset of the aisle between them."""
        pitch = dice.uniform(2.7, 3.1)
        s = self.first + 3.0 + pitch * (np.arange(int((self.last - self.first - 6.0) / pitch)) + 0.5)
        near = [(float(x), road_edge - 3.2, -np.pi / 2) for x in s]
        far = [(float(x), road_edge - self.depth + 3.2, np.pi / 2) for x in s]
        return near + far, road_edge - self.depth / 2


@dataclass(frozen=True, eq=False)
class Corridor:
    """The road of a corridor scene (local frame: the reference line starts at the origin heading east)."""

    forward: Carriageway
    backward: Carriageway
    width: float
    shoulder: float  # width of the generic drivable strip right of the road; 0 when there is none
    walkways: tuple[FloatArray, ...]  # centre lines

    @property
    def right_edge(self) -> float:
        """Return the lateral offset of the road's right edge (forward lanes lie between it and 0)."""
        return -self.forward.n_lanes * self.width

    @property
    def left_edge(self) -> float:
        """Return the lateral offset of the road's left edge (oncoming lanes lie between 0 and it)."""
        return self.backward.n_lanes * self.width

    def oncoming_s(self, path: Polyline, vertex: int) -> float:
        """Return the arc length on an oncoming lane's path abreast of a forward reference vertex."""
        return float(path.arclength[ROAD_VERTICES - 1 - int(np.clip(vertex, 0, ROAD_VERTICES - 1))])


def _reference(dice: Dice, curved: bool) -> Polyline:
    curvature = np.zeros(ROAD_VERTICES - 1)
    if curved:
        start = dice.uniform(40.0, 190.0)
        sign = 1.0 if dice.chance(0.5) else -1.0
        for _ in range(1 + int(dice.chance(0.35))):
            radius = dice.uniform(50.0, 300.0)
            length = min(dice.uniform(40.0, 140.0), 1.6 * radius)  # at most about 90 degrees
            curvature += curve_profile(
                ROAD_VERTICES - 1, start, length, dice.uniform(12.0, 25.0), sign / radius
            )
            start += length + dice.uniform(15.0, 40.0)
            sign = -sign
    return road_line((0.0, 0.0), 0.0, curvature)


def _build_road(dice: Dice, road_map: RoadMap, kind: str) -> Corridor:
    rng = dice.rng
    width = dice.uniform(3.2, 3.8)
    beside_carpark = kind in ("carpark", "carpark_start")
    n_forward = dice.pick("forward_lanes", {1: 0.5, 2: 0.5} if beside_carpark else {1: 0.25, 2: 0.45, 3: 0.3})
    n_backward = dice.pick("oncoming_lanes", {1: 0.55, 2: 0.45})
    speed_limit = SPEED_LIMITS[int(rng.integers(len(SPEED_LIMITS)))]
    reference = _reference(dice, curved=kind == "curve")
    sections = cut_sections(ROAD_VERTICES, rng.integers(40, 91, size=16).tolist())
    forward, backward = two_way_road(road_map, reference, sections, n_forward, n_backward, width, speed_limit)
    keep = sample_indices(ROAD_VERTICES, BASELINE_STRIDE)
    right = -n_forward * width
    shoulder = dice.uniform(2.0, 2.8) if not beside_carpark and dice.chance(0.5) else 0.0
    if shoulder:
        road_map.add_area(
            "drivable_areas", ring(reference.offset(right)[keep], reference.offset(right - shoulder)[keep])
        )
    walkways = []
    sides = [(n_backward * width + 0.3, 1.0)] + ([] if beside_carpark else [(right - shoulder - 0.3, -1.0)])
    for inner, direction in sides:
        walk_width = dice.uniform(2.0, 3.2)
        outer = inner + direction * walk_width
        road_map.add_area("walkways", ring(reference.offset(inner)[keep], reference.offset(outer)[keep]))
        walkways.append(reference.offset(inner + direction * walk_width / 2))
    return Corridor(forward, backward, width, shoulder, tuple(walkways))


def _add_carpark(dice: Dice, road_map: RoadMap, corridor: Corridor, ego_vertex: int) -> Carpark:
    """Add a car park beside the forward carriageway around the ego's position."""
    first = int(np.clip(ego_vertex + dice.rng.integers(-60, -15), 10, ROAD_VERTICES - 80))
    carpark = Carpark(
        first, min(first + int(dice.rng.integers(70, 121)), ROAD_VERTICES - 5), dice.uniform(25.0, 35.0)
    )
    span = first + sample_indices(carpark.last - first + 1, BASELINE_STRIDE)
    edge = corridor.right_edge
    reference = corridor.forward.reference
    road_map.add_area(
        "carpark_areas", ring(reference.offset(edge)[span], reference.offset(edge - carpark.depth)[span])
    )
    return carpark


def _crosswalk(dice: Dice, road_map: RoadMap, corridor: Corridor, vertex: int, ego: EgoMotion) -> list[Track]:
    """Add a crosswalk across the road at a reference vertex; return the pedestrians crossing it."""
    reference = corridor.forward.reference
    length = int(dice.rng.integers(3, 5))
    span = np.arange(vertex, vertex + length + 1)
    left = corridor.left_edge + 0.3
    right = corridor.right_edge - corridor.shoulder - 0.3
    road_map.add_area("crosswalks", ring(reference.offset(left)[span], reference.offset(right)[span]))
    pedestrians = []
    for _ in range(int(dice.rng.integers(1, 4))):
        s = vertex + dice.uniform(0.5, length - 0.5)
        ends = reference.poses(np.array([s, s]), np.array([left + 1.2, right - 1.2]))[:, :2]
        if dice.chance(0.5):
            ends = ends[::-1]
        track = crossing_walker(dice.rng, ego, ends)
        if track is not None:
            pedestrians.append(track)
    return pedestrians


def _vertex_at(path: Polyline, s: float) -> int:
    """Return the first vertex of a lane path at arc length >= s, leaving room for a crosswalk before the road's end."""
    return min(int(np.searchsorted(path.arclength, s)), ROAD_VERTICES - 6)


def _traffic(
    dice: Dice, corridor: Corridor, ego_lane: int | None, ego_vertex: int, ego_speed: float
) -> list[Track]:
    """Return the road users and objects around the ego other than its lead, follower and pedestrians to yield to."""
    rng = dice.rng
    tracks = _roadside(dice, corridor, ego_lane, ego_vertex)  # first: vehicles give way to what stands
    forward, backward = corridor.forward, corridor.backward
    # Adjacent lanes, same direction.
    for lane in range(forward.n_lanes):
        if lane == ego_lane:
            continue
        path = forward.lane_path(lane)
        for offset in np.sort(rng.uniform(-35.0, 60.0, size=int(rng.integers(0, 3)))):
            speed = (
                max(0.0, ego_speed + dice.uniform(-3.0, 3.0)) if ego_speed > 0 or dice.chance(0.5) else 0.0
            )
            tracks.append(
                vehicle(rng, path, float(path.arclength[ego_vertex]) + offset, _cruise(dice, speed))
            )
    # Oncoming lanes.
    for lane in range(backward.n_lanes):
        path = backward.lane_path(lane)
        for offset in rng.uniform(-40.0, 120.0, size=int(rng.integers(0, 4))):
            speed = 0.0 if dice.chance(0.15) else dice.uniform(4.0, 16.0)
            s0 = corridor.oncoming_s(path, ego_vertex + int(offset))
            tracks.append(vehicle(rng, path, s0, _cruise(dice, speed)))
    if dice.chance(0.3):  # a far agent
        lane = int(rng.integers(forward.n_lanes))
        path = forward.lane_path(lane)
        tracks.append(
            vehicle(
                rng,
                path,
                float(path.arclength[ego_vertex]) + dice.uniform(60.0, 95.0),
                _cruise(dice, dice.uniform(3.0, 15.0)),
            )
        )
    return tracks


def _cruise(dice: Dice, speed: float) -> Transition:
    """Return a speed profile that holds or gently changes `speed` (standing still stays still)."""
    if speed <= 0.0:
        return Transition.constant(0.0)
    start = dice.uniform(-2.0, 4.0)
    return Transition(speed, max(0.0, speed + dice.uniform(-2.0, 2.0)), start, start + dice.uniform(2.0, 5.0))


def _roadside(dice: Dice, corridor: Corridor, ego_lane: int | None, ego_vertex: int) -> list[Track]:
    """Return cyclists, parked vehicles, pedestrians on walkways, construction objects and debris."""
    rng = dice.rng
    tracks: list[Track] = []
    reference = corridor.forward.reference
    right = corridor.right_edge
    ahead = float(reference.arclength[ego_vertex])
    if dice.pick("cyclist", {True: 0.3, False: 0.7}):
        lateral = right - corridor.shoulder / 2 if corridor.shoulder else right + 0.6
        speed = Transition.constant(dice.uniform(3.0, 6.5))
        tracks.append(
            moving_track(
                "bicycle",
                object_size(rng, "bicycle"),
                reference,
                ahead + dice.uniform(-20.0, 50.0),
                speed,
                Transition.constant(lateral),
            )
        )
    if corridor.shoulder and dice.chance(0.5):  # stopped vehicles on the shoulder
        for offset in rng.uniform(-30.0, 80.0, size=int(rng.integers(1, 3))):
            pose = reference.poses(ahead + offset, right - corridor.shoulder / 2)
            tracks.append(parked(rng, "vehicle", "car", pose))
    strollers = int(rng.integers(0, 4))
    tracks.extend(
        stroller(rng, corridor.walkways[int(rng.integers(len(corridor.walkways)))]) for _ in range(strollers)
    )
    if dice.pick("construction", {True: 0.4, False: 0.6}):
        start = ahead + dice.uniform(5.0, 70.0)
        # A closed lane (never the ego's), or a row along one of the road's edges.
        closable = [-(k + 0.5) * corridor.width for k in range(corridor.forward.n_lanes) if k != ego_lane]
        closable += [(k + 0.5) * corridor.width for k in range(corridor.backward.n_lanes)]
        if dice.chance(0.5):
            lateral = closable[int(rng.integers(len(closable)))]
        else:
            lateral = right - 0.25 if dice.chance(0.6) else corridor.left_edge + 0.25
        kind = "traffic_cone" if dice.chance(0.6) else "barrier"
        spacing = dice.uniform(2.5, 5.0) if kind == "traffic_cone" else dice.uniform(2.6, 3.2)
        tracks += row_of_statics(rng, reference, start, int(rng.integers(3, 9)), spacing, lateral, kind)
        if dice.chance(0.4):
            tracks.append(
                parked(
                    rng,
                    "czone_sign",
                    "czone_sign",
                    reference.poses(start - 3.0, lateral - 0.3 * np.sign(lateral)),
                )
            )
    if dice.chance(0.3):  # debris or a bin by the road
        line = corridor.walkways[int(rng.integers(len(corridor.walkways)))]
        vertex = int(np.clip(ego_vertex + rng.integers(-30, 60), 0, ROAD_VERTICES - 1))
        tracks.append(
            parked(rng, "generic_object", "generic_object", (*line[vertex], dice.uniform(-np.pi, np.pi)))
        )
    return tracks


def _route(dice: Dice, forward: Carriageway, ego_block: int) -> tuple[str, list[str]]:
    """Return the route variant and the route roadblock ids (the ego's carriageway from its roadblock on)."""
    ids = [block.id for block in forward.blocks]
    variant = dice.pick("route_variant", ROUTE_VARIANTS)
    if variant == "with_previous" and ego_block >= 2:
        return variant, ids[max(0, ego_block - 2 * int(dice.rng.integers(1, 3))) :]
    if variant == "starts_ahead" and ego_block + 1 < len(ids):
        return variant, ids[ego_block + 1 :]
    if variant == "missing_connector" and ego_block + 1 < len(ids):
        connectors = list(range(ego_block + 1, min(len(ids), ego_block + 6), 2))
        dropped = connectors[int(dice.rng.integers(len(connectors)))]
        return variant, ids[ego_block:dropped] + ids[dropped + 1 :]
    return "normal", ids[ego_block:]


def _carpark_users(
    dice: Dice, corridor: Corridor, carpark: Carpark, spots: list[tuple[float, float, float]], aisle: float
) -> list[Track]:
    """Return parked vehicles in the spots, and now and then a vehicle or pedestrians moving in the aisle."""
    rng = dice.rng
    reference = corridor.forward.reference
    occupancy = dice.uniform(0.5, 0.9)
    tracks = []
    for s, lateral, towards_aisle in spots:
        if rng.random() < occupancy:
            x, y, heading = reference.poses(s, lateral)
            facing = towards_aisle if rng.random() < 0.5 else towards_aisle + np.pi
            tracks.append(parked(rng, "vehicle", "car", (x, y, heading + facing + rng.normal(0.0, 0.04))))
    first, last = carpark.first, carpark.last
    if dice.chance(0.5):
        path = Polyline.from_points(reference.offset(aisle)[first : last + 1])
        path = path if dice.chance(0.5) else path.reversed()
        tracks.append(
            moving_track(
                "vehicle",
                vehicle_size(rng),
                path,
                dice.uniform(5.0, 40.0),
                Transition.constant(dice.uniform(1.5, 4.0)),
            )
        )
    for _ in range(int(rng.integers(0, 3))):
        s = dice.uniform(first + 5.0, last - 5.0)
        ends = reference.poses(
            np.array([s, s + dice.uniform(-5.0, 5.0)]), np.array([aisle + 5.0, aisle - 5.0])
        )[:, :2]
        tracks.append(walker(rng, ends[0], ends[1], dice.uniform(0.8, 1.4), dice.uniform(-3.0, 2.0)))
    return tracks


def _parked_ego(
    dice: Dice, corridor: Corridor, spots: list[tuple[float, float, float]]
) -> tuple[int, EgoMotion, int]:
    """Return the ego's spot index, its motion (waiting, or creeping towards the aisle) and the nearest reference vertex."""
    index = int(dice.rng.integers(len(spots)))
    s, lateral, towards_aisle = spots[index]
    x, y, heading = corridor.forward.reference.poses(s, lateral)
    heading += towards_aisle + dice.rng.normal(0.0, 0.03)
    direction = np.array([np.cos(heading), np.sin(heading)])
    rear_axle = np.array([x, y]) - REAR_AXLE_TO_CENTER * direction
    path = Polyline.from_points(rear_axle + np.outer([-10.0, 30.0], direction))
    speed = Transition.constant(0.0)
    if dice.chance(0.3):
        go = dice.uniform(0.5, 2.5)
        speed = Transition(0.0, dice.uniform(0.5, 1.2), go, go + dice.uniform(1.5, 3.0))
    return index, ego_motion(path, 10.0, speed), round(s)


def corridor_scene(dice: Dice, kind: str, first_id: int) -> SceneDraft:
    """Return a corridor scene of the given kind (straight, curve, carpark, carpark_start)."""
    rng = dice.rng
    road_map = RoadMap(first_id)
    ego_vertex = int(rng.integers(110, 151))
    corridor = _build_road(dice, road_map, kind)
    forward = corridor.forward
    info: dict[str, object] = {
        "kind": kind,
        "n_fwd": forward.n_lanes,
        "n_onc": corridor.backward.n_lanes,
        "lane_width": corridor.width,
        "speed_limit": forward.lanes[0][0].speed_limit,
    }
    carpark = (
        _add_carpark(dice, road_map, corridor, ego_vertex) if kind in ("carpark", "carpark_start") else None
    )
    if carpark is not None and kind == "carpark_start":
        spots, aisle = carpark.spots(dice, corridor.right_edge)
        spot, ego, ego_vertex = _parked_ego(dice, corridor, spots)
        tracks = _carpark_users(dice, corridor, carpark, spots[:spot] + spots[spot + 1 :], aisle)
        tracks += _traffic(dice, corridor, None, ego_vertex, 0.0)
        block = forward.block_index(ego_vertex)
        route = [b.id for b in forward.blocks[block + block % 2 :]]
        info.update(route_variant="parked", ego_v0=0.0)
        return SceneDraft(road_map, ego, vary_sightings(dice, tracks), route, "straight", info=info)

    if forward.block_index(ego_vertex) % 2:  # keep the rear axle off the connector gap
        ego_vertex += 2
    lane = int(rng.integers(forward.n_lanes))
    path = forward.lane_path(lane)
    s0 = float(path.arclength[ego_vertex])
    speed_class, speed = ego_initial_speed(dice)
    # Humans take curves at a comfortable lateral acceleration.
    curvature = np.abs(path.curvature(np.linspace(s0 - 20.0, s0 + 120.0, 141))).max()
    speed = min(speed, float(np.sqrt(CURVE_LATERAL_ACCELERATION / max(curvature, 1e-6))))
    behaviour = dice.pick("lead", QUEUE_BEHAVIOURS if speed <= 0.0 else LEAD_BEHAVIOURS)
    if behaviour == "stopped" and speed > MAX_SPEED_BEHIND_STOPPED:
        behaviour = "brake"  # a fast ego would start braking long before a standing lead comes into sight
    ego_speed, lead = lead_plan(dice, behaviour, speed, path, s0)
    lateral, command = None, "unknown" if dice.chance(0.1) else "straight"
    if (
        forward.n_lanes > 1
        and behaviour in ("none", "cruise")
        and speed > MIN_LANE_CHANGE_SPEED
        and dice.pick("lane_change", {True: 0.25, False: 0.75})
    ):
        target = lane - 1 if lane == forward.n_lanes - 1 or (lane > 0 and dice.chance(0.5)) else lane + 1
        start = dice.uniform(-2.0, 0.5)
        lateral = Transition(
            0.0, (lane - target) * corridor.width, start, start + dice.uniform(*LANE_CHANGE_DURATION)
        )
        command = "left" if target < lane else "right"
    crossing = dice.pick("crossing", {True: 0.3, False: 0.7})
    crosswalk_ahead = dice.uniform(15.0, 80.0)
    if crossing and behaviour == "none" and lateral is None and (speed <= 0.0 or dice.chance(0.6)):
        # The ego waits for (or stops for) pedestrians on a crosswalk just ahead.
        ego_speed = braking(speed, dice.uniform(1.5, 3.5), dice.uniform(0.0, 0.6))
        crosswalk_ahead = ego_speed.distance_until_settled() + dice.uniform(2.0, 4.0)
    ego = ego_motion(path, s0, ego_speed, lateral)
    tracks = [lead] if lead is not None else []
    if dice.chance(0.4):  # a follower replaying the ego's speed a moment later, behind it in the same lane
        delay = dice.uniform(0.8, 1.6)
        size = vehicle_size(rng)
        follower_speed = Transition(
            ego_speed.start, ego_speed.end, ego_speed.t1 + delay, ego_speed.t2 + delay
        )
        s_follower = (
            s0 + float(ego_speed.integral(-delay)) - (EGO_REAR_LENGTH + size[0] / 2 + dice.uniform(2.0, 5.0))
        )
        tracks.append(moving_track("vehicle", size, path, s_follower, follower_speed))
    if crossing:
        tracks += _crosswalk(
            dice, road_map, corridor, _vertex_at(path, s0 + EGO_FRONT_LENGTH + crosswalk_ahead), ego
        )
    if carpark is not None:
        tracks += _carpark_users(dice, corridor, carpark, *carpark.spots(dice, corridor.right_edge))
    tracks += _traffic(dice, corridor, lane, ego_vertex, speed)
    variant, route = _route(dice, forward, forward.block_index(ego_vertex))
    info.update(
        route_variant=variant,
        ego_lane_index=lane,
        ego_speed_class=speed_class,
        ego_v0=speed,
        lead=behaviour,
        lane_change=command if lateral is not None else None,
        crossing_pedestrian=crossing,
        shoulder=corridor.shoulder > 0,
    )
    return SceneDraft(road_map, ego, vary_sightings(dice, tracks), route, command, info=info)
