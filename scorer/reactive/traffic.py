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

The loop is scalar because the devkit's is sequential: each update reads geometries the previous ones wrote,
and ties between equidistant leads are settled by the STRtrees' traversal, so the trees are built as the
devkit builds them, over the same geometries in the same order.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import shapely
import shapely.ops

from scorer.geometry import EGO_HALF_LENGTH, EGO_HALF_WIDTH, FloatArray, box_corners, principal_value
from scorer.reactive.agents import IdmVehicle, ParkingCandidate, StartingTraffic, box_polygon
from scorer.reactive.idm import Lead, idm_update
from scorer.trajectory import StateIndex
from scorer.versions import IdmTraffic

EGO = "ego"
STEP_S = 0.1  # the IDM's tspan: the scorer's proposal sampling interval
SIMPLIFY_TOLERANCE = 1e-5


@dataclass(frozen=True)
class IdmUpdate:
    """One IDM update: the step, the vehicle, what it followed and its state before and after."""

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


@dataclass
class _Agent:
    """A simulated vehicle's state during the loop (`nuplan` `IDMAgent`)."""

    start: IdmVehicle
    progress: float
    speed: float

    def pose(self) -> tuple[float, float, float]:
        return self.start.path.state_at(self.start.path.clamp(self.progress))

    def box(self) -> shapely.Polygon:
        return box_polygon(*self.pose(), self.start.length, self.start.width)

    def projected_footprint(self, headway_time: float) -> shapely.Geometry:
        path, half_length = self.start.path, self.start.length / 2
        lower = path.clamp(self.progress - half_length)
        upper = path.clamp(self.progress + half_length + self.speed * headway_time)
        ahead = shapely.buffer(
            shapely.linestrings(path.between(lower, upper)), self.start.width / 2, cap_style="flat"
        )
        return shapely.union_all([ahead, self.box()])


def ego_boxes(states: FloatArray) -> list[shapely.Polygon]:
    """Return the ego's box as the IDM sees it at each state (T, 11): centred on the rear axle."""
    corners = box_corners(
        states[:, StateIndex.X],
        states[:, StateIndex.Y],
        states[:, StateIndex.HEADING],
        EGO_HALF_LENGTH,
        EGO_HALF_WIDTH,
    )
    return list(shapely.polygons(corners))


def _lead_of(
    agent: _Agent, agents: dict[str, _Agent], occupancy: dict[str, shapely.Geometry], ego_state: FloatArray
) -> tuple[str | None, Lead]:
    """Return what `agent` follows (`NavsimIDMAgentManager.propagate_agents`)."""
    track = agent.start.track
    path = agent.start.path
    ahead = shapely.buffer(
        shapely.linestrings(path.to_go(path.clamp(agent.progress))), agent.start.width / 2, cap_style="flat"
    )
    names = list(occupancy)
    geometries = list(occupancy.values())
    hits = [names[index] for index in shapely.STRtree(geometries).query(ahead, predicate="intersects")]
    if track not in hits:
        raise ValueError(f"vehicle {track}: its path does not meet its own footprint (the devkit asserts)")
    if len(hits) == 1:
        return None, Lead(path.end - agent.progress, 0.0, agent.start.length / 2)
    others = [name for name in hits if name not in track]
    own = occupancy[track]
    nearest = others[int(shapely.STRtree([occupancy[name] for name in others]).nearest(own))]
    near_own, near_other = shapely.ops.nearest_points(own, occupancy[nearest])
    distance = float(near_own.distance(near_other))
    heading = agent.pose()[2]
    if EGO in nearest:
        speed = float(np.hypot(ego_state[StateIndex.VELOCITY_X], ego_state[StateIndex.VELOCITY_Y]))
        relative_heading = float(ego_state[StateIndex.HEADING]) - heading
    else:
        speed = agents[nearest].speed
        relative_heading = agents[nearest].pose()[2] - heading
    return nearest, Lead(distance, speed * float(np.cos(principal_value(relative_heading))), 0.0)


def simulate_traffic(start: StartingTraffic, ego_states: FloatArray, config: IdmTraffic) -> VehicleSteps:
    """Return the vehicles of steps 1..len(ego_states) - 1 reacting to the ego's simulated states (T, 11)."""
    agents = {vehicle.track: _Agent(vehicle, vehicle.progress, vehicle.speed) for vehicle in start.agents}
    occupancy: dict[str, shapely.Geometry] = {
        vehicle.track: box_polygon(*vehicle.pose, vehicle.length, vehicle.width) for vehicle in start.agents
    }
    target_velocity = {vehicle.track: vehicle.target_velocity for vehicle in start.agents}
    parked = {candidate: box_polygon(*candidate.box) for candidate in start.parking}
    ego = ego_boxes(ego_states)
    steps = []
    updates: list[IdmUpdate] = []
    out_of_range: dict[str, int] = {}
    for step in range(1, len(ego_states)):
        ego_state = ego_states[step - 1]
        occupancy[EGO] = ego[step - 1]
        _leave_range(agents, occupancy, ego_state, config.radius, step, out_of_range)
        for track, agent in agents.items():
            occupancy = dict(
                zip(
                    occupancy,
                    shapely.simplify(list(occupancy.values()), SIMPLIFY_TOLERANCE, preserve_topology=True),
                    strict=True,
                )
            )
            lead_track, lead = _lead_of(agent, agents, occupancy, ego_state)
            before = (agent.progress, agent.speed)
            agent.progress, agent.speed = idm_update(
                agent.progress, agent.speed, lead, target_velocity[track], config, STEP_S
            )
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
            occupancy[track] = agent.projected_footprint(config.headway_time)
        steps.append(_vehicles_of_step(agents.values(), parked, config))
    return VehicleSteps(steps=tuple(steps), updates=tuple(updates), out_of_range=out_of_range)


def _leave_range(
    agents: dict[str, _Agent],
    occupancy: dict[str, shapely.Geometry],
    ego_state: FloatArray,
    radius: float,
    step: int,
    out_of_range: dict[str, int],
) -> None:
    """Remove the vehicles farther than `radius` from the ego's rear axle, from the simulation for good."""
    if not agents:
        return
    # Imported here: scoring and caching the log-replay versions start without scipy (docs/engine.md, "Start-up").
    from scipy.spatial.distance import cdist

    centres = np.array([agent.pose()[:2] for agent in agents.values()])
    distances = cdist(ego_state[None, : StateIndex.HEADING], centres)[0]
    for track in np.array(list(agents))[distances > radius].tolist():
        del agents[track], occupancy[track]
        out_of_range[track] = step


def _vehicles_of_step(
    agents: Iterable[_Agent],
    parked: dict[ParkingCandidate, shapely.Polygon],
    config: IdmTraffic,
) -> tuple[tuple[str, float, float, float, float, float], ...]:
    """Return the vehicles the scorer sees at a step: the simulated ones, then the parked ones they leave free."""
    vehicles = [(agent.start.track, *agent.pose(), agent.start.length, agent.start.width) for agent in agents]
    if config.add_open_loop_parked_vehicles and parked:
        boxes = [box_polygon(*vehicle[1:]) for vehicle in vehicles]
        for candidate, polygon in parked.items():
            if not boxes or not shapely.intersects(boxes, polygon).any():
                vehicles.append((candidate.track, *candidate.box))
    return tuple(vehicles)
