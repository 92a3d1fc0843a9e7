"""Intersection scenes: a signalised four-way junction of two two-way roads.

Local frame: the junction's centre at the origin; arm a brings traffic heading pi/2 + a * pi/2 (the ego
always comes from the south arm, heading north). The intersection polygon covers the box between the
arms; every approach has roadblock connectors for straight, left and right, with lane connectors that
carry the traffic lights (the green axis is north-south or east-west).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scorer.geometry import EGO_FRONT_LENGTH, FloatArray
from scorer.synth.actors import (
    crossing_walker,
    object_size,
    parked,
    row_of_statics,
    stroller,
    vehicle,
    vehicle_size,
)
from scorer.synth.draft import (
    SPEED_LIMITS,
    Dice,
    SceneDraft,
    ego_initial_speed,
    lead_plan,
    vary_sightings,
)
from scorer.synth.motion import EgoMotion, Track, Transition, braking, ego_motion, moving_track
from scorer.synth.polyline import Polyline, bezier, concatenate, road_line
from scorer.synth.roadmap import (
    BlockRecord,
    Carriageway,
    LaneRecord,
    RoadMap,
    connect,
    cut_sections,
    ring,
    two_way_road,
)

MOVEMENTS = {"straight": 0.6, "left": 0.2, "right": 0.2}
MAX_SPEED = {"straight": 14.0, "left": 10.0, "right": 10.0}  # m/s at the current frame; turns slow down first
TURN_SPEED = (3.0, 4.5)  # m/s through a turn: the tracker of the scorer follows 2 Hz poses with some lag
EXIT_ARM = {"straight": 2, "left": 3, "right": 1}  # arm offset of the exit, seen from the approach
ROUTE_VARIANTS = {"normal": 0.8, "with_previous": 0.1, "starts_ahead": 0.1}
CHAMFER = 1.0  # m cut off the corners of the intersection polygon
CIRCLE_TANGENT = 0.5523  # Bezier handle of a quarter circle, per unit radius


@dataclass(frozen=True, eq=False)
class Arm:
    """One road meeting the junction: its inbound and outbound carriageways."""

    inbound: Carriageway
    outbound: Carriageway

    @property
    def heading(self) -> float:
        """Return the heading of inbound traffic."""
        return float(self.inbound.reference.heading[-1])


@dataclass(frozen=True, eq=False)
class Junction:
    """The arms, the movement connectors and the box of a junction."""

    arms: tuple[Arm, ...]
    movements: dict[tuple[int, str], BlockRecord]
    movement_lanes: dict[tuple[int, str], list[LaneRecord]]
    movement_pairs: dict[tuple[int, str], list[tuple[int, int]]]  # (inbound lane, exit lane) of each
    half_size: tuple[float, float]  # half-extent of the box along x (east) and y (north)
    width: float

    def depth(self, arm: int) -> float:
        """Return the distance from the centre to the box edge an arm meets."""
        return self.half_size[1] if arm % 2 == 0 else self.half_size[0]

    def path(self, arm: int, movement: str, lane: int) -> Polyline:
        """Return the centre line from the far end of an inbound lane through a movement to the far end of its exit lane.

        A movement that does not leave from `lane` is taken from the lane it leaves from.
        """
        pairs = self.movement_pairs[(arm, movement)]
        index = next((i for i, (lane_in, _) in enumerate(pairs) if lane_in == lane), 0)
        lane_in, lane_out = pairs[index]
        exit_road = self.arms[(arm + EXIT_ARM[movement]) % 4].outbound
        return concatenate(
            [
                self.arms[arm].inbound.lane_path(lane_in).points,
                self.movement_lanes[(arm, movement)][index].centre,
                exit_road.lane_path(lane_out).points,
            ]
        )


def _movement_pairs(n_in: int, n_out: int, movement: str) -> list[tuple[int, int]]:
    """Return the (inbound lane, exit lane) indices a movement joins, from the left-most pair."""
    if movement == "straight":
        return [(k, k) for k in range(min(n_in, n_out))]
    return [(0, 0)] if movement == "left" else [(n_in - 1, n_out - 1)]


def _connector_centre(
    start: FloatArray, start_heading: float, end: FloatArray, end_heading: float, straight: bool
) -> FloatArray:
    delta = end - start
    along_start = abs(float(delta @ [np.cos(start_heading), np.sin(start_heading)]))
    along_end = abs(float(delta @ [np.cos(end_heading), np.sin(end_heading)]))
    tangent = along_start / 3.0 if straight else CIRCLE_TANGENT * 0.5 * (along_start + along_end)
    return bezier(start, start_heading, end, end_heading, tangent)


def _build_junction(dice: Dice, road_map: RoadMap) -> Junction:
    rng = dice.rng
    width = dice.uniform(3.2, 3.7)
    lanes_north_south = dice.pick("ns_lanes", {1: 0.5, 2: 0.5})
    lanes_east_west = dice.pick("ew_lanes", {1: 0.5, 2: 0.5})
    margin = dice.uniform(6.0, 9.0)  # right turns then have radii of about 8 to 11 m
    speed_limit = SPEED_LIMITS[int(rng.integers(len(SPEED_LIMITS)))]
    half_size = (lanes_north_south * width + margin, lanes_east_west * width + margin)
    arms = []
    for arm in range(4):
        n_lanes = lanes_north_south if arm % 2 == 0 else lanes_east_west
        heading = np.pi / 2 + arm * np.pi / 2
        direction = np.array([np.cos(heading), np.sin(heading)])
        length = int(rng.integers(120, 171))
        depth = half_size[1] if arm % 2 == 0 else half_size[0]
        reference = road_line(-direction * (depth + length), heading, np.zeros(length))
        sections = cut_sections(length + 1, rng.integers(40, 91, size=6).tolist())
        arms.append(Arm(*two_way_road(road_map, reference, sections, n_lanes, n_lanes, width, speed_limit)))
    movements, movement_lanes, movement_pairs = {}, {}, {}
    for arm in range(4):
        inbound = arms[arm].inbound
        for movement, offset in EXIT_ARM.items():
            exit_road = arms[(arm + offset) % 4].outbound
            pairs = _movement_pairs(inbound.n_lanes, exit_road.n_lanes, movement)
            lanes = [(inbound.lanes[-1][k_in], exit_road.lanes[0][k_out]) for k_in, k_out in pairs]
            centres = [
                _connector_centre(
                    lane_in.centre[-1],
                    arms[arm].heading,
                    lane_out.centre[0],
                    float(exit_road.reference.heading[0]),
                    movement == "straight",
                )
                for lane_in, lane_out in lanes
            ]
            block = connect(
                road_map, inbound.blocks[-1], exit_road.blocks[0], lanes, centres, width, speed_limit
            )
            movements[(arm, movement)] = block
            movement_lanes[(arm, movement)] = [
                lane for lane in road_map.lane_connectors if lane.block == block.id
            ]
            movement_pairs[(arm, movement)] = pairs
    x, y = half_size
    c = CHAMFER
    road_map.add_area(
        "intersections",
        np.array(
            [
                [x - c, -y],
                [x, -y + c],
                [x, y - c],
                [x - c, y],
                [-x + c, y],
                [-x, y - c],
                [-x, -y + c],
                [-x + c, -y],
            ]
        ),
    )
    junction = Junction(tuple(arms), movements, movement_lanes, movement_pairs, half_size, width)
    _add_sidewalks(dice, road_map, junction)
    return junction


def _arm_frame(junction: Junction, arm: int) -> tuple[FloatArray, FloatArray]:
    """Return the unit vector of inbound traffic on an arm and its left normal."""
    heading = junction.arms[arm].heading
    return np.array([np.cos(heading), np.sin(heading)]), np.array([-np.sin(heading), np.cos(heading)])


def _add_sidewalks(dice: Dice, road_map: RoadMap, junction: Junction) -> None:
    """Add a crosswalk across every arm's mouth (inside the box) and walkways along both sides of every arm."""
    for arm in range(4):
        along, left = _arm_frame(junction, arm)
        half_road = junction.arms[arm].inbound.n_lanes * junction.width
        depth = junction.depth(arm)
        near, far = -depth + 0.5, -depth + 0.5 + dice.uniform(3.0, 4.0)
        corners = [near * along + side * (half_road + 1.5) * left for side in (-1, 1)]
        corners += [far * along + side * (half_road + 1.5) * left for side in (1, -1)]
        road_map.add_area("crosswalks", np.array(corners))
    for arm in range(4):
        reference = junction.arms[arm].inbound.reference
        half_road = junction.arms[arm].inbound.n_lanes * junction.width
        for side in (-1.0, 1.0):
            inner, outer = side * (half_road + 0.5), side * (half_road + 3.0)
            road_map.add_area("walkways", ring(reference.offset(inner)[::2], reference.offset(outer)[::2]))


def _crossing_pedestrians(dice: Dice, junction: Junction, arms: list[int], ego: EgoMotion) -> list[Track]:
    """Return pedestrians walking over the crosswalks of the given arms, kept clear of the ego."""
    pedestrians = []
    for _ in range(int(dice.rng.integers(1, 4))):
        arm = arms[int(dice.rng.integers(len(arms)))]
        along, left = _arm_frame(junction, arm)
        half_road = junction.arms[arm].inbound.n_lanes * junction.width
        centre = (-junction.depth(arm) + 2.2) * along
        ends = np.stack([centre - (half_road + 1.2) * left, centre + (half_road + 1.2) * left])
        if dice.chance(0.5):
            ends = ends[::-1]
        track = crossing_walker(dice.rng, ego, ends)
        if track is not None:
            pedestrians.append(track)
    return pedestrians


def _queue(dice: Dice, path: Polyline, stop_s: float, count: int) -> tuple[list[Track], float]:
    """Return `count` vehicles standing in line with the first front bumper at `stop_s`, and where the queue ends."""
    tracks = []
    for _ in range(count):
        size = vehicle_size(dice.rng)
        tracks.append(moving_track("vehicle", size, path, stop_s - size[0] / 2, Transition.constant(0.0)))
        stop_s -= size[0] + dice.uniform(1.5, 3.5)
    return tracks, stop_s


def _cross_traffic(dice: Dice, junction: Junction, green_axis: int) -> list[Track]:
    """Return the other approaches' traffic: moving through on green, queued at the line on red; and leaving traffic."""
    rng = dice.rng
    tracks: list[Track] = []
    for arm in (1, 2, 3):
        inbound = junction.arms[arm].inbound
        edge = inbound.reference.length
        for lane in range(inbound.n_lanes):
            if arm % 2 == green_axis:
                for _ in range(int(rng.integers(0, 3))):
                    movement = dice.pick(
                        "traffic_movement",
                        {
                            "straight": 0.6,
                            "left": 0.2 * (lane == 0),
                            "right": 0.2 * (lane == inbound.n_lanes - 1),
                        },
                    )
                    path = junction.path(arm, movement, lane)
                    speed = dice.uniform(5.0, 12.0) if movement == "straight" else dice.uniform(3.5, 6.0)
                    tracks.append(
                        vehicle(rng, path, edge + dice.uniform(-70.0, 15.0), Transition.constant(speed))
                    )
            else:
                queue, _ = _queue(
                    dice, inbound.lane_path(lane), edge - dice.uniform(0.5, 2.0), int(rng.integers(0, 3))
                )
                tracks += queue
    for arm in range(4):  # traffic leaving the junction
        outbound = junction.arms[arm].outbound
        for lane in range(outbound.n_lanes):
            if dice.chance(0.4):
                path = outbound.lane_path(lane)
                tracks.append(
                    vehicle(rng, path, dice.uniform(10.0, 80.0), Transition.constant(dice.uniform(4.0, 13.0)))
                )
    return tracks


def _roadside(dice: Dice, junction: Junction) -> list[Track]:
    """Return cyclists, walkway pedestrians, construction objects and debris around the junction."""
    rng = dice.rng
    tracks: list[Track] = []
    if dice.pick("cyclist", {True: 0.3, False: 0.7}):
        arm = int(rng.integers(4))
        road = junction.arms[arm].outbound
        path = road.lane_path(road.n_lanes - 1)
        tracks.append(
            moving_track(
                "bicycle",
                object_size(rng, "bicycle"),
                path,
                dice.uniform(0.0, 60.0),
                Transition.constant(dice.uniform(3.0, 6.0)),
                Transition.constant(-0.5 * junction.width + 0.6),
            )
        )
    for _ in range(int(rng.integers(0, 4))):
        arm = int(rng.integers(4))
        reference = junction.arms[arm].inbound.reference
        side = 1.0 if dice.chance(0.5) else -1.0
        tracks.append(
            stroller(
                rng, reference.offset(side * (junction.arms[arm].inbound.n_lanes * junction.width + 1.75))
            )
        )
    if dice.pick("construction", {True: 0.4, False: 0.6}):
        arm = int(rng.integers(1, 4))
        road = junction.arms[arm].outbound
        kind = "traffic_cone" if dice.chance(0.6) else "barrier"
        lateral = -road.n_lanes * junction.width + 0.25
        start = dice.uniform(8.0, 60.0)
        tracks += row_of_statics(
            rng, road.reference, start, int(rng.integers(3, 8)), dice.uniform(2.6, 4.5), lateral, kind
        )
        if dice.chance(0.4):
            tracks.append(
                parked(rng, "czone_sign", "czone_sign", road.reference.poses(start - 3.0, lateral - 0.5))
            )
    if dice.chance(0.3):
        x, y = junction.half_size
        corner = np.array([x + 2.0, y + 2.0]) * np.array(
            [1.0 if dice.chance(0.5) else -1.0, 1.0 if dice.chance(0.5) else -1.0]
        )
        tracks.append(parked(rng, "generic_object", "generic_object", (*corner, dice.uniform(-np.pi, np.pi))))
    return tracks


@dataclass(frozen=True, eq=False)
class EgoPlan:
    """The ego's part of an intersection scene."""

    speed_class: str
    speed: float  # at the current frame
    s0: float  # rear-axle arc length on the ego's path at the current frame
    profile: Transition
    ahead: list[Track]  # vehicles queued or driving in front of the ego


def _turn_approach(dice: Dice, speed: float, edge_s: float) -> tuple[float, Transition]:
    """Return the arc length and speed profile of an ego that slows to a turning speed before the junction."""
    turning = dice.uniform(*TURN_SPEED)
    if speed <= turning:
        return edge_s - EGO_FRONT_LENGTH - dice.uniform(2.0, 25.0), Transition.constant(speed)
    start = dice.uniform(0.0, 0.5)
    profile = Transition(speed, turning, start, start + 1.5 * (speed - turning) / dice.uniform(1.2, 2.5))
    return edge_s - EGO_FRONT_LENGTH - profile.distance_until_settled() - dice.uniform(0.0, 8.0), profile


def _ego_plan(dice: Dice, path: Polyline, edge_s: float, movement: str, ego_red: bool) -> EgoPlan:
    """Return the ego's plan: waiting or stopping at a red light (maybe behind a queue), or driving through on green."""
    speed_class, speed = ego_initial_speed(dice)
    speed = min(speed, MAX_SPEED[movement])
    line = edge_s - EGO_FRONT_LENGTH  # rear-axle arc length with the front bumper on the stop line
    if ego_red and movement == "straight" and speed > 0.0 and dice.chance(0.2):
        # At the line when the light turned red: the ego drives on.
        speed = max(speed, dice.uniform(7.0, 11.0))
        return EgoPlan(speed_class, speed, line - dice.uniform(0.5, 6.0), Transition.constant(speed), [])
    if ego_red:
        count = int(dice.rng.integers(1, 3)) if dice.chance(0.5) else 0
        queue, tail = _queue(dice, path, edge_s - dice.uniform(0.5, 2.0), count)
        stop_front = tail - dice.uniform(1.5, 4.0) if queue else edge_s - dice.uniform(0.5, 3.0)
        if speed <= 0.0:
            return EgoPlan(speed_class, 0.0, stop_front - EGO_FRONT_LENGTH, Transition.constant(0.0), queue)
        profile = braking(speed, dice.uniform(2.0, 3.5), dice.uniform(0.0, 0.8))
        return EgoPlan(
            speed_class,
            speed,
            stop_front - EGO_FRONT_LENGTH - profile.distance_until_settled(),
            profile,
            queue,
        )
    if speed <= 0.0:  # green: the ego moves off from the line
        go = dice.uniform(0.0, 1.5)
        target = dice.uniform(4.0, 8.0) if movement == "straight" else dice.uniform(*TURN_SPEED)
        profile = Transition(0.0, target, go, go + 1.5 * target / dice.uniform(1.2, 2.5))
        return EgoPlan(speed_class, 0.0, line - dice.uniform(0.5, 3.0), profile, [])
    if movement != "straight":
        if dice.chance(0.2):  # already turning
            speed = min(speed, dice.uniform(*TURN_SPEED))
            return EgoPlan(
                speed_class, speed, edge_s + dice.uniform(0.0, 4.0), Transition.constant(speed), []
            )
        s0, profile = _turn_approach(dice, speed, edge_s)
        return EgoPlan(speed_class, speed, s0, profile, [])
    s0 = edge_s + dice.uniform(0.0, 6.0) if dice.chance(0.2) else line - dice.uniform(3.0, 45.0)
    behaviour = "cruise" if dice.chance(0.35) else "none"
    profile, lead = lead_plan(dice, behaviour, speed, path, s0)
    return EgoPlan(speed_class, speed, s0, profile, [lead] if lead is not None else [])


def _route(
    dice: Dice, junction: Junction, movement: str, ego_s: float, edge_s: float
) -> tuple[str, list[str]]:
    """Return the route variant and the route: the south approach, the movement's connector, the exit road."""
    approach = junction.arms[0].inbound
    exit_road = junction.arms[EXIT_ARM[movement]].outbound
    ids = (
        [b.id for b in approach.blocks]
        + [junction.movements[(0, movement)].id]
        + [b.id for b in exit_road.blocks]
    )
    first = approach.block_index(round(ego_s)) if ego_s < edge_s else len(approach.blocks)
    variant = dice.pick("route_variant", ROUTE_VARIANTS)
    if variant == "with_previous" and first >= 2:
        return variant, ids[first - 2 :]
    if variant == "starts_ahead" and first + 1 < len(ids):
        return variant, ids[first + 1 :]
    return "normal", ids[first:]


def intersection_scene(dice: Dice, first_id: int) -> SceneDraft:
    """Return an intersection scene: the ego comes from the south and goes straight, left or right."""
    rng = dice.rng
    road_map = RoadMap(first_id)
    junction = _build_junction(dice, road_map)
    movement = dice.pick("movement", MOVEMENTS)
    approach = junction.arms[0].inbound
    lane = {"left": 0, "right": approach.n_lanes - 1}.get(movement, int(rng.integers(approach.n_lanes)))
    path = junction.path(0, movement, lane)
    edge_s = approach.reference.length  # the approach lanes end on the box edge
    ego_red = dice.pick("ego_red", {True: 0.4, False: 0.6})
    plan = _ego_plan(dice, path, edge_s, movement, ego_red)
    s0 = max(plan.s0, 10.0)
    if s0 < edge_s and approach.block_index(round(s0)) % 2:  # keep the rear axle off a connector gap
        s0 -= 2.0
    ego = ego_motion(path, s0, plan.profile)
    green_axis = 1 if ego_red else 0
    lights = [
        (lane_record.id, arm % 2 != green_axis)
        for (arm, _), lanes in junction.movement_lanes.items()
        for lane_record in lanes
    ]
    crossing = dice.pick("crossing", {True: 0.45, False: 0.55})
    tracks = list(plan.ahead)
    if crossing:  # pedestrians cross the arms whose traffic waits
        tracks += _crossing_pedestrians(dice, junction, [0, 2] if ego_red else [1, 3], ego)
    tracks += _cross_traffic(dice, junction, green_axis)
    tracks += _roadside(dice, junction)
    variant, route = _route(dice, junction, movement, s0, edge_s)
    info: dict[str, object] = {
        "kind": "intersection",
        "movement": movement,
        "ego_red": ego_red,
        "n_ns": approach.n_lanes,
        "n_ew": junction.arms[1].inbound.n_lanes,
        "lane_width": junction.width,
        "speed_limit": approach.lanes[0][0].speed_limit,
        "route_variant": variant,
        "ego_lane_index": lane,
        "ego_speed_class": plan.speed_class,
        "ego_v0": plan.speed,
        "vehicles_ahead": len(plan.ahead),
        "crossing_pedestrian": crossing,
    }
    return SceneDraft(road_map, ego, vary_sightings(dice, tracks), route, movement, lights, info)
