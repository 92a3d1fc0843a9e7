"""The reactive simulation: 40 IDM steps of 0.1 s against a given ego trajectory, and the vehicles of each step
(docs/engine.md, "Reactive traffic: one step").

As NAVSIM's `NavsimIDMTrafficAgents.simulate_traffic_agents` with `NavsimIDMAgentManager`: step k = 1..40
reads the ego state k - 1, whose box, as the IDM sees it, is centred on the simulated **rear axle**. Per step:
1. the ego's box goes into the occupancy (a dict: the simulated vehicles in building order, "ego" after them);
2. vehicles farther than the radius from the ego's rear axle (scipy's `cdist`) leave, for good;
3. vehicle by vehicle: every geometry of the occupancy is simplified (1e-5, topology kept) and stored back;
   the path ahead from the clamped progress, buffered by half the width with flat caps, is queried against an
   STRtree of the occupancy; if it meets more than the vehicle's own geometry, the lead is the other hit
   nearest (an STRtree of the other hits, built in query order, skipping ids that are substrings of the
   vehicle's track) at the distance of shapely's `nearest_points`, with speed v * cos(principal value of
   the heading difference), v the ego's rear-axle speed (numpy's `hypot`) for an id containing "ego" and
   the vehicle's IDM speed otherwise; else the path's end is a standing lead (distance = path end - the
   unclamped progress, length_rear = half the length). The IDM update (`scorer.reactive.idm`) follows, and the
   vehicle's geometry becomes its projected footprint: the path between clamp(p - L/2) and
   clamp(p + L/2 + v * headway), buffered, united with its box. Later vehicles of the step see it.
4. the step's vehicles: every simulated vehicle's box at its clamped progress, then each parking candidate
   (`scorer.reactive.agents`) whose recorded box touches none of them.

The loop is scalar because the devkit's is sequential: each update reads geometries the previous ones wrote.
The occupancy is lazy (`scorer.reactive.occupancy`): a geometry is built and simplified only when a path ahead
may meet it, so a lead search that meets nothing but the vehicle's own geometry costs no GEOS call (and the
devkit's assertion that the path ahead meets that geometry is tested only while it is the box at the start:
later the footprint holds a box centred where the path ahead starts). Of the geometries the path ahead meets
(shapely's `intersects`, as the STRtree query's predicate) the one strictly nearest by GEOS's distance (what
the STRtree's `nearest` minimises) is the devkit's lead; where several are equally near (often at 0: a
footprint overlapping two others), or a hit's name lies within the vehicle's track, the STRtrees are built as
the devkit builds them, over the same geometries in the same order, and their traversal settles it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple, TypeVar

import numpy as np
import shapely
import shapely.ops

from scorer.geometry import EGO_HALF_LENGTH, EGO_HALF_WIDTH, FloatArray, box_corners, principal_value_of
from scorer.reactive import geos
from scorer.reactive.agents import IdmVehicle, ParkingCandidate, StartingTraffic, box_polygon
from scorer.reactive.idm import Idm, Lead
from scorer.reactive.occupancy import (
    BOUND_SLACK,
    BUFFER_REACH,
    Bound,
    Envelope,
    LazyOccupancy,
    Recent,
    bound_of,
    box_capsule,
    box_is_simplified,
    envelope_of,
    path_between_bound,
    path_to_go_bound,
)
from scorer.reactive.paths import LanePath
from scorer.trajectory import StateIndex
from scorer.versions import IdmTraffic

EGO = "ego"
T = TypeVar("T")
STEP_S = 0.1  # the IDM's tspan: the scorer's proposal sampling interval
_SIMULATIONS = itertools.count()
# Where the range filter's own distance decides (`_leave_range`): beyond a millionth of the radius.
RANGE_TIE = 1e-6
_BOXES: Recent[shapely.Polygon] = Recent(4096)
_EGO_IS_SIMPLIFIED = box_is_simplified(2 * EGO_HALF_LENGTH, 2 * EGO_HALF_WIDTH)


class IdmUpdate(NamedTuple):
    """One IDM update: the step, the vehicle, what it followed and its state before and after (a tuple: one
    is made per vehicle and step)."""

    step: int
    track: str
    lead_track: str | None  # None: the end of its path
    lead: Lead
    before: tuple[float, float]  # progress, speed
    after: tuple[float, float]
    target_velocity: float


@dataclass(frozen=True, eq=False)
class VehicleSteps:
    """The vehicles of steps 1..40: per step (track, x, y, heading, length, width) in the devkit's order."""

    steps: tuple[tuple[tuple[str, float, float, float, float, float], ...], ...]
    updates: tuple[IdmUpdate, ...]
    out_of_range: dict[str, int]  # track -> the step at which it left the radius


class _Agent:
    """A simulated vehicle's state during the loop (`nuplan` `IDMAgent`): its progress and speed, and what a
    step reads of them, computed once per update: the progress clamped to its path and its pose there. What
    its start fixes (its path's ends, its size's halves) is kept once per simulation: read at every update."""

    __slots__ = (
        "clamped",
        "first",
        "half_length",
        "half_width",
        "last",
        "length",
        "path",
        "pose",
        "progress",
        "reach",
        "speed",
        "start",
        "track",
        "updated",
        "widened",
        "width",
    )

    def __init__(self, start: IdmVehicle) -> None:
        self.start = start
        self.track, self.path, self.length, self.width = start.track, start.path, start.length, start.width
        self.first, self.last = start.path.progress[0], start.path.progress[-1]  # `LanePath.clamp`'s bounds
        self.half_length, self.half_width = start.length / 2, start.width / 2
        self.widened = self.half_width * BUFFER_REACH  # a buffer by half its width reaches that far
        self.reach = math.hypot(self.half_length, self.half_width)  # its box's circumscribed circle
        self.updated = False  # its occupancy holds its projected footprint, no longer its box at the start
        self.move(start.progress, start.speed)

    def move(self, progress: float, speed: float) -> None:
        """Set the vehicle's progress and speed (an IDM update)."""
        self.progress, self.speed = progress, speed
        self.clamped = clamped = max(self.first, min(progress, self.last))
        self.pose = self.path.state_at(clamped)

    def projected_footprint(
        self, headway_time: float
    ) -> tuple[Hashable, Envelope, Callable[[], Bound], Callable[[], shapely.Geometry]]:
        """Return what defines the vehicle's projected footprint now (its key), what holds it (an envelope,
        capsules) and the function that builds it. The envelope is a square around the box centre (on the
        path): the box's circumscribed circle, and the path's points between the bounds lie no farther from
        the centre than their progress does."""
        path, length, width, first, last = self.path, self.length, self.width, self.first, self.last
        progress, half_length = self.progress, self.half_length
        lower = max(first, min(progress - half_length, last))
        upper = max(first, min(progress + half_length + self.speed * headway_time, last))
        pose, clamped = self.pose, self.clamped
        reach = max(max(clamped - lower, upper - clamped) + self.widened, self.reach)
        reach += BOUND_SLACK
        envelope = pose[0] - reach, pose[1] - reach, pose[0] + reach, pose[1] + reach

        def bound() -> Bound:
            capsules, envelopes = path_between_bound(path, lower, upper, width / 2)
            box, box_envelope = bound_of([box_capsule(*pose, length, width)])
            return capsules + box, envelopes + box_envelope

        def build() -> shapely.Geometry:
            ahead = geos.flat_buffer(geos.line(path.between(lower, upper)), width / 2)
            return geos.union(ahead, _box(*pose, length, width))

        return (path.identity, lower, upper, pose, length, width), envelope, bound, build

    def box_meets(self, polygon: shapely.Polygon, envelope: Envelope) -> bool:
        """Return whether the vehicle's box now meets `polygon` (held within `envelope`): tested by GEOS only
        where their envelopes meet (touching counts)."""
        x, y, heading = self.pose
        radius = self.reach + BOUND_SLACK  # `_box_envelope`'s
        low_x, low_y, high_x, high_y = envelope
        return (
            x - radius <= high_x
            and low_x <= x + radius
            and y - radius <= high_y
            and low_y <= y + radius
            and geos.intersects(_box(x, y, heading, self.length, self.width), polygon)
        )


def _box(x: float, y: float, heading: float, length: float, width: float) -> shapely.Polygon:
    """Return `box_polygon`, memoised: a vehicle's box at a step serves its footprint and the test of the
    parked vehicles, and a vehicle standing still keeps its box."""
    key = (x, y, heading, length, width)
    return _BOXES.get_or_make(key, partial(box_polygon, *key))


def _box_envelope(pose: tuple[float, float, float], length: float, width: float) -> Envelope:
    """Return an envelope of the box of `length` x `width` centred at the pose: the square around its
    circumscribed circle."""
    radius = math.hypot(length / 2, width / 2) + BOUND_SLACK
    return pose[0] - radius, pose[1] - radius, pose[0] + radius, pose[1] + radius


def _ego_corners(states: FloatArray) -> FloatArray:
    """Return the corners (T, 4, 2) of the ego's box as the IDM sees it at each state (T, 11): centred on the
    rear axle."""
    return box_corners(
        states[:, StateIndex.X],
        states[:, StateIndex.Y],
        states[:, StateIndex.HEADING],
        EGO_HALF_LENGTH,
        EGO_HALF_WIDTH,
    )


class _PathAhead:
    """The path ahead of a vehicle, buffered by half its width with flat caps, as the devkit's lead search
    queries it; the buffer is built only where a test needs it.

    Whether a geometry meets the buffer is decided without it where the answer is sure: the buffer holds every
    point of its line but the two ends (a flat cap passes through each), so a geometry meeting the line
    short of its ends by the slack meets the buffer; the buffer lies within `BUFFER_REACH` times the distance
    of the line (GEOS's simplification of its input line), so a geometry farther than that and the slack
    does not (the margin the occupancy's capsule test keeps for GEOS's rounding). The rest asks GEOS's
    buffer: about one search in seventeen builds it."""

    def __init__(self, points: FloatArray, half_width: float) -> None:
        self._points = points
        self._half_width = half_width
        self._line: shapely.LineString | None = None
        self._inner: shapely.LineString | None | bool = False  # False: not made yet
        self._buffer: shapely.Geometry | None = None

    def buffer(self) -> shapely.Geometry:
        """Return the buffered path ahead, as the devkit builds it."""
        if self._buffer is None:
            self._buffer = geos.flat_buffer(self.line(), self._half_width)
        return self._buffer

    def line(self) -> shapely.LineString:
        """Return the path ahead as a line."""
        if self._line is None:
            self._line = geos.line(self._points)
        return self._line

    def meets(self, geometry: shapely.Geometry) -> bool:
        """Return `shapely.intersects(geometry, self.buffer())`."""
        inner = self._inner_line()
        if inner is not None and geos.intersects(geometry, inner):
            return True
        if geos.distance(geometry, self.line()) > self._half_width * BUFFER_REACH + BOUND_SLACK:
            return False
        return geos.intersects(geometry, self.buffer())

    def _inner_line(self) -> shapely.LineString | None:
        """Return the line short of its ends by `BOUND_SLACK` (None: an end segment is too short)."""
        if self._inner is False:
            # Any point of the line's interior serves: Python floats, not the devkit's operations.
            (x0, y0), (x1, y1) = self._points[:2].tolist()
            (x2, y2), (x3, y3) = self._points[-2:].tolist()
            first_length, last_length = math.hypot(x1 - x0, y1 - y0), math.hypot(x3 - x2, y3 - y2)
            if min(first_length, last_length) <= 2 * BOUND_SLACK:
                self._inner = None
            else:
                inner = self._points.copy()
                inner[0] = (
                    x0 + (x1 - x0) * (BOUND_SLACK / first_length),
                    y0 + (y1 - y0) * (BOUND_SLACK / first_length),
                )
                inner[-1] = (
                    x3 + (x2 - x3) * (BOUND_SLACK / last_length),
                    y3 + (y2 - y3) * (BOUND_SLACK / last_length),
                )
                self._inner = geos.line(inner)
        return self._inner


def _inside_box(x: float, y: float, box: tuple[float, float, float], length: float, width: float) -> bool:
    """Return whether (x, y) lies inside the box of `length` x `width` centred at the pose `box` by more than
    `BOUND_SLACK` across and along it: then a path ahead starting there surely meets the box as the devkit's
    lead search holds it (the box, simplified; GEOS's buffer of the path ahead).

    The points of the path ahead near its first point lie inside the box too, and all but its ends lie inside
    the buffer (`_PathAhead`). The box's corners and this test round their products and sums by ulps of the
    coordinates (this test turns by Python's cosine and sine, the box by numpy's: an ulp apart, as in
    `box_capsule`), and simplifying the box moves its sides by at most the tolerance (it moves none,
    `box_is_simplified`): nothing against the margin."""
    center_x, center_y, heading = box
    cos, sin = math.cos(heading), math.sin(heading)
    offset_x, offset_y = x - center_x, y - center_y
    along, across = offset_x * cos + offset_y * sin, offset_y * cos - offset_x * sin
    return abs(along) < length / 2 - BOUND_SLACK and abs(across) < width / 2 - BOUND_SLACK


class _TreeOrderNeeded(Exception):
    """Equally near leads (or an odd name): only the devkit's STRtrees can say which one it follows."""


def _lead_of(
    agent: _Agent, agents: dict[str, _Agent], occupancy: LazyOccupancy, ego_state: FloatArray
) -> tuple[str | None, Lead]:
    """Return what `agent` follows (`NavsimIDMAgentManager.propagate_agents`)."""
    track, path, clamped, half_width = agent.track, agent.path, agent.clamped, agent.half_width
    near = occupancy.around(path.to_go_envelope(clamped, agent.widened + BOUND_SLACK), track)
    if near:
        ahead_key = (path.identity, clamped, half_width)
        near = occupancy.near(near, ahead_key, partial(path_to_go_bound, path, clamped, half_width))
    free_road = None, Lead(agent.last - agent.progress, 0.0, agent.half_length)
    # After its first update a vehicle's footprint holds its box, centred where its path ahead starts: the
    # devkit's assertion that the path ahead meets the vehicle's own geometry holds without a test; before,
    # it holds where the path ahead starts well inside the box at the start.
    meets_own = agent.updated or _inside_box(
        *path.to_go_start(clamped), agent.start.pose, agent.length, agent.width
    )
    if not near and meets_own:
        return free_road
    ahead = _PathAhead(path.to_go(clamped), half_width)
    if not meets_own and not ahead.meets(occupancy.geometry(track)):
        raise ValueError(f"vehicle {track}: its path does not meet its own footprint (the devkit asserts)")
    try:
        nearest = _nearest_hit(track, ahead, near, occupancy)
    except _TreeOrderNeeded:
        nearest = _nearest_hit_in_tree_order(track, ahead.buffer(), occupancy)
    if nearest is None:
        return free_road
    own = occupancy.geometry(track)  # built only now: where the path ahead meets another geometry
    near_own, near_other = shapely.ops.nearest_points(own, occupancy.geometry(nearest))
    distance = float(near_own.distance(near_other))
    heading = agent.pose[2]
    if EGO in nearest:
        speed = float(np.hypot(ego_state[StateIndex.VELOCITY_X], ego_state[StateIndex.VELOCITY_Y]))
        relative_heading = float(ego_state[StateIndex.HEADING]) - heading
    else:
        speed = agents[nearest].speed
        relative_heading = agents[nearest].pose[2] - heading
    return nearest, Lead(distance, speed * float(np.cos(principal_value_of(relative_heading))), 0.0)


def _nearest_hit(track: str, ahead: _PathAhead, near: list[str], occupancy: LazyOccupancy) -> str | None:
    """Return the geometry the path `ahead` meets nearest to the vehicle's own (None: only its own), the
    devkit's choice wherever one is strictly nearest (GEOS's distance, as its STRtree's `nearest` measures)."""
    hits = [name for name in near if ahead.meets(occupancy.geometry(name))]
    if any(name in track for name in hits):
        raise _TreeOrderNeeded
    if len(hits) <= 1:
        return hits[0] if hits else None
    distances = shapely.distance([occupancy.geometry(name) for name in hits], occupancy.geometry(track))
    nearest = np.flatnonzero(distances == distances.min())
    if len(nearest) > 1:
        raise _TreeOrderNeeded
    return hits[int(nearest[0])]


def _nearest_hit_in_tree_order(track: str, ahead: shapely.Geometry, occupancy: LazyOccupancy) -> str:
    """Return the devkit's lead, its STRtrees built over the same geometries in the same order: the query's
    hits over every geometry, then `nearest` over the hits not named within the vehicle's track."""
    names = occupancy.names()
    geometries = [occupancy.geometry(name) for name in names]
    hits = [names[index] for index in shapely.STRtree(geometries).query(ahead, predicate="intersects")]
    others = [name for name in hits if name not in track]
    own = occupancy.geometry(track)
    return others[int(shapely.STRtree([occupancy.geometry(name) for name in others]).nearest(own))]


def simulate_traffic(start: StartingTraffic, ego_states: FloatArray, config: IdmTraffic) -> VehicleSteps:
    """Return the vehicles of steps 1..len(ego_states) - 1 reacting to the ego's simulated states (T, 11)."""
    agents = {vehicle.track: _Agent(vehicle) for vehicle in start.agents}
    occupancy = LazyOccupancy()
    # The ego's boxes are this simulation's own: its keys name them within it alone.
    simulation = next(_SIMULATIONS)
    for vehicle in start.agents:
        bound = bound_of([box_capsule(*vehicle.pose, vehicle.length, vehicle.width)])
        occupancy.set(
            vehicle.track,
            ("box", *vehicle.pose, vehicle.length, vehicle.width),
            envelope_of(bound[1]),
            partial(_given, bound),
            partial(box_polygon, *vehicle.pose, vehicle.length, vehicle.width),
            box_is_simplified(vehicle.length, vehicle.width),
        )
    target_velocity = {vehicle.track: vehicle.target_velocity for vehicle in start.agents}
    parked = _parked(start, config)
    idm = Idm(config)
    ego_corners = _ego_corners(ego_states)
    ego = shapely.polygons(ego_corners)
    # The ego box's long axis, from its rear edge's middle to its front edge's (corners FL, RL, RR, FR).
    ego_capsules = np.concatenate(
        [
            (ego_corners[:, 1] + ego_corners[:, 2]) / 2,
            (ego_corners[:, 0] + ego_corners[:, 3]) / 2,
            np.full((len(ego_corners), 1), EGO_HALF_WIDTH),
        ],
        axis=1,
    ).tolist()
    steps = []
    updates: list[IdmUpdate] = []
    out_of_range: dict[str, int] = {}
    for step in range(1, len(ego_states)):
        ego_state = ego_states[step - 1]
        bound = bound_of([tuple(ego_capsules[step - 1])])
        occupancy.set(
            EGO,
            (EGO, simulation, *ego_states[step - 1, : StateIndex.HEADING + 1].tolist()),
            envelope_of(bound[1]),
            partial(_given, bound),
            partial(_given, ego[step - 1]),
            _EGO_IS_SIMPLIFIED,
        )
        _leave_range(agents, occupancy, ego_state, config.radius, step, out_of_range)
        for track, agent in agents.items():
            occupancy.simplify_round()
            lead_track, lead = _lead_of(agent, agents, occupancy, ego_state)
            before = (agent.progress, agent.speed)
            agent.move(*idm.update(agent.progress, agent.speed, lead, target_velocity[track], STEP_S))
            agent.updated = True
            updates.append(
                IdmUpdate(
                    step,
                    track,
                    lead_track,
                    lead,
                    before,
                    (agent.progress, agent.speed),
                    target_velocity[track],
                )
            )
            occupancy.set(track, *agent.projected_footprint(config.headway_time))
        steps.append(_vehicles_of_step(agents, parked))
    return VehicleSteps(steps=tuple(steps), updates=tuple(updates), out_of_range=out_of_range)


def _given(value: T) -> T:
    return value


def _leave_range(
    agents: dict[str, _Agent],
    occupancy: LazyOccupancy,
    ego_state: FloatArray,
    radius: float,
    step: int,
    out_of_range: dict[str, int],
) -> None:
    """Remove the vehicles farther than `radius` from the ego's rear axle, from the simulation for good.

    The devkit measures with scipy's `cdist`; Python's sqrt(dx * dx + dy * dy) is within a few ulps of it, so
    it decides every vehicle but those within a millionth of the radius, which `cdist` decides."""
    ego_x, ego_y = float(ego_state[StateIndex.X]), float(ego_state[StateIndex.Y])
    leaving = []
    for track, agent in agents.items():
        x, y, _ = agent.pose
        distance = math.sqrt((x - ego_x) * (x - ego_x) + (y - ego_y) * (y - ego_y))
        if abs(distance - radius) <= radius * RANGE_TIE:
            distance = _devkit_distance(ego_state, x, y)
        if distance > radius:
            leaving.append(track)
    for track in leaving:
        del agents[track]
        occupancy.remove(track)
        out_of_range[track] = step


def _devkit_distance(ego_state: FloatArray, x: float, y: float) -> float:
    """Return the distance from the ego's rear axle to (x, y) as the devkit's range filter measures it."""
    # Imported here: scoring and caching the log-replay versions start without scipy (docs/engine.md, "Start-up").
    from scipy.spatial.distance import cdist

    return float(cdist(ego_state[None, : StateIndex.HEADING], np.array([[x, y]]))[0, 0])


class _Parked(NamedTuple):
    """A parking candidate, its recorded box and the simulated vehicles whose boxes may come near it."""

    candidate: ParkingCandidate
    polygon: shapely.Polygon
    envelope: Envelope
    reaching: tuple[str, ...]  # the tracks of the vehicles whose path passes within a box's reach of it


def _parked(start: StartingTraffic, config: IdmTraffic) -> list[_Parked]:
    """Return the parking candidates of a simulation (none where the configuration keeps no parked vehicles),
    each with the vehicles that may meet it: a vehicle's box stays centred on its path, so its envelope
    (`_box_envelope`) lies within the envelope of the path's vertices widened by its radius and the slack (an
    interpolated point lies between its vertices up to ulps); the others never meet the candidate's envelope,
    so no step tests them."""
    if not config.add_open_loop_parked_vehicles:
        return []
    reaches = [
        (vehicle.track, _path_envelope(vehicle.path, math.hypot(vehicle.length / 2, vehicle.width / 2)))
        for vehicle in start.agents
    ]
    parked = []
    for candidate in start.parking:
        envelope = _box_envelope(candidate.box[:3], *candidate.box[3:])
        low_x, low_y, high_x, high_y = envelope
        reaching = tuple(
            track
            for track, (around_low_x, around_low_y, around_high_x, around_high_y) in reaches
            if around_low_x <= high_x
            and low_x <= around_high_x
            and around_low_y <= high_y
            and low_y <= around_high_y
        )
        parked.append(_Parked(candidate, box_polygon(*candidate.box), envelope, reaching))
    return parked


def _path_envelope(path: LanePath, radius: float) -> Envelope:
    """Return the envelope of the path's vertices, widened by `radius` and twice the slack."""
    return path.to_go_envelope(path.start, radius + 2 * BOUND_SLACK)


def _vehicles_of_step(
    agents: dict[str, _Agent], parked: list[_Parked]
) -> tuple[tuple[str, float, float, float, float, float], ...]:
    """Return the vehicles the scorer sees at a step: the simulated ones, then the parked ones they leave free
    (a simulated box is built only where its envelope meets a parked one's)."""
    vehicles = [(agent.track, *agent.pose, agent.length, agent.width) for agent in agents.values()]
    for candidate, polygon, envelope, reaching in parked:
        if not any(agents[track].box_meets(polygon, envelope) for track in reaching if track in agents):
            vehicles.append((candidate.track, *candidate.box))
    return tuple(vehicles)
