"""One IDM update of one vehicle, as nuPlan's `IDMAgent.propagate` with the forward-Euler policy
(docs/engine.md, "Reactive traffic: one step").

`IDMPolicy.solve_forward_euler_idm_policy` evaluates `idm_model` on a state of progress 0 and the vehicle's
speed v: s* = gap + v * headway + v * (v - v_lead) / (2 * sqrt(a_max * b_max)), s_alpha = max(d_lead - 0 -
length_rear, gap), acceleration a_max * (1 - (v / v_target) ** 4 - (s* / s_alpha) ** 2); then progress
0 + dt * v and speed v + dt * clip(acceleration, -b_max, a_max), and `propagate` adds the progress to the
vehicle's (never clamped) and keeps max(speed, 0). Scalar on purpose: each vehicle's update reads the leads
that earlier vehicles of the same step have just moved, and Python floats round each operation as the devkit's
do, in its order.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from scorer.versions import IdmTraffic


class Lead(NamedTuple):
    """What a vehicle follows: its distance ahead (m), speed along the vehicle's heading (m/s), rear length
    (a tuple: one is made per vehicle and step)."""

    distance: float
    velocity: float
    length_rear: float


class Idm:
    """The IDM of one configuration, its constants computed once (the same floats the devkit's expressions
    give: one update is made per vehicle and step)."""

    __slots__ = ("_accel_max", "_comfortable_braking", "_headway_time", "_lowest", "_min_gap")

    def __init__(self, config: IdmTraffic) -> None:
        self._comfortable_braking = 2 * math.sqrt(config.accel_max * config.decel_max)
        self._min_gap = config.min_gap_to_lead_agent
        self._headway_time = config.headway_time
        self._accel_max = config.accel_max
        self._lowest = config.decel_max * -1

    def update(
        self, progress: float, speed: float, lead: Lead, target_velocity: float, dt: float
    ) -> tuple[float, float]:
        """Return the vehicle's progress and speed after `dt` seconds behind `lead`."""
        min_gap = self._min_gap
        distance, velocity, length_rear = lead
        desired_gap = (
            min_gap + speed * self._headway_time + (speed * (speed - velocity)) / self._comfortable_braking
        )
        gap = max(distance - 0.0 - length_rear, min_gap)
        acceleration = self._accel_max * (1 - (speed / target_velocity) ** 4 - (desired_gap / gap) ** 2)
        moved = 0.0 + dt * speed
        next_speed = speed + dt * min(max(self._lowest, acceleration), self._accel_max)
        return progress + moved, max(next_speed, 0.0)
