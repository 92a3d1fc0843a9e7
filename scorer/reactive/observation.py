"""What the scorer observes under reactive traffic: the recorded current frame, the simulated vehicles, and
every other object replayed from the log (docs/engine.md, "Reactive traffic: the observation").

NAVSIM's `AbstractTrafficAgentsPolicy.simulate_environment` gives the scorer 41 detection lists: step 0 is
every object of the current frame as recorded (not the interpolated observation's step 0, which holds
objects first seen later and re-wrapped headings), step k the policy's vehicles of step k followed by the
non-vehicle objects of the interpolated log observation at step k. Logged futures of vehicles are never
read. The scorer keys objects by track and takes each one's type and speed from its first appearance, so for
a current vehicle that is its recorded object; red lights are appended as in the log replay.

Everything but the simulated vehicles depends on the scene alone: it is the metric cache's observation of a
reactive version (`base_observation`), into which each scored trajectory's vehicles are written
(`with_vehicles`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from scorer.geometry import FloatArray, box_corners
from scorer.observation import Observation
from scorer.reactive.agents import StartingTraffic
from scorer.reactive.traffic import VehicleSteps, simulate_traffic
from scorer.scene import AGENT_CATEGORIES, Frame
from scorer.versions import IdmTraffic

VEHICLE_TYPE = "VEHICLE"


def base_observation(frame: Frame, replayed: Observation) -> Observation:
    """Return the observation of a reactive version without its simulated vehicles: the current `frame`'s
    objects at step 0, and from step 1 on the non-vehicle objects of the log observation `replayed`."""
    current = frame.tracks
    column_of = {track: column for column, track in enumerate(replayed.tokens)}
    is_vehicle = np.array([kind == VEHICLE_TYPE for kind in replayed.object_types], dtype=bool)
    later = [column for column in np.flatnonzero(~is_vehicle) if replayed.tokens[column] not in set(current)]
    tokens = (*current, *(replayed.tokens[column] for column in later))
    steps = replayed.present.shape[0]
    present = np.zeros((steps, len(tokens)), dtype=bool)
    corners = np.full((steps, len(tokens), 4, 2), np.nan)
    boxes = frame.boxes
    present[0, : len(current)] = True
    corners[0, : len(current)] = box_corners(
        boxes[:, 0], boxes[:, 1], boxes[:, 6], boxes[:, 3] / 2.0, boxes[:, 4] / 2.0
    )
    # Non-vehicles from step 1 on: the current ones' replayed columns, then those first seen later.
    replayed_columns = [column_of[track] for track in current] + later
    own = np.array([not is_vehicle[column] for column in replayed_columns], dtype=bool)
    source = np.array(replayed_columns, dtype=np.intp)[own]
    present[1:, own] = replayed.present[1:, source]
    corners[1:, own] = replayed.corners[1:, source]
    is_agent = np.isin(np.array(frame.categories, dtype=str), AGENT_CATEGORIES)
    speed = np.where(is_agent, np.hypot(frame.velocities[:, 0], frame.velocities[:, 1]), 0.0)
    return Observation(
        tokens=tokens,
        object_types=(
            *(category.upper() for category in frame.categories),
            *(replayed.object_types[c] for c in later),
        ),
        is_agent=np.concatenate([is_agent, replayed.is_agent[later]]),
        first_speed=np.concatenate([speed, replayed.first_speed[later]]),
        present=present,
        boxes=corners[present],
        red_lights=replayed.red_lights,
    )


def with_vehicles(base: Observation, vehicles: VehicleSteps) -> Observation:
    """Return `base` with the vehicles of steps 1.. (`scorer.reactive.traffic.simulate_traffic`) written in."""
    column_of = {track: column for column, track in enumerate(base.tokens)}
    seen = [vehicle for vehicles_of_step in vehicles.steps for vehicle in vehicles_of_step]
    present, corners = base.present.copy(), base.corners.copy()
    if seen:
        step = np.repeat(np.arange(1, len(vehicles.steps) + 1), [len(at) for at in vehicles.steps])
        tracks, *box_columns = zip(*seen, strict=True)
        column = np.array([column_of[track] for track in tracks])
        # One array per column: `np.column_stack` of the tuples took three times as long (the same floats).
        x, y, heading, length, width = (np.array(values, dtype=np.float64) for values in box_columns)
        present[step, column] = True
        corners[step, column] = box_corners(x, y, heading, length / 2.0, width / 2.0)
    return replace(base, present=present, boxes=corners[present])


def reacting_observation(
    traffic: StartingTraffic, base: Observation, ego_states: FloatArray, config: IdmTraffic
) -> Observation:
    """Return the observation of a trajectory's simulated states (41, 11): `base` with the vehicles reacting to
    it."""
    return with_vehicles(base, simulate_traffic(traffic, ego_states, config))
