"""What a scene kind produces before export, and the draws shared by every kind."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from scorer.geometry import EGO_FRONT_LENGTH
from scorer.synth.actors import gap_ahead, seen_in_history_only, seen_once, vehicle_size
from scorer.synth.motion import FRAME_TIMES, EgoMotion, Track, Transition, braking, moving_track
from scorer.synth.polyline import Polyline
from scorer.synth.roadmap import RoadMap

T = TypeVar("T")

# nuPlan speed limits: 20, 25, 30, 35, 40 mph, or unknown (PDM-Closed then assumes 15 m/s).
SPEED_LIMITS: tuple[float | None, ...] = (8.94, 11.18, 13.41, 15.65, 17.88, None)
EGO_SPEED_CLASSES = {
    "standstill": (0.0, 0.0),
    "slow": (0.5, 5.0),
    "medium": (5.0, 12.0),
    "fast": (12.0, 21.0),
}
COMMANDS = ("left", "straight", "right", "unknown")
MIN_GAP = 2.0  # m kept between the ego's front and a lead's rear in every frame


@dataclass(frozen=True, eq=False)
class Dice:
    """The draws of one scene: a few categorical choices stratified over the split, everything else random.

    `strata` holds, per choice, the scene's value of a low-discrepancy sequence over the split, so
    that every option appears at its share in any run of consecutive scenes.
    """

    rng: np.random.Generator
    strata: Mapping[str, float]

    def pick(self, choice: str, weights: Mapping[T, float]) -> T:
        """Return an option with probability proportional to its weight."""
        fraction = self.strata[choice] if choice in self.strata else self.rng.random()
        options = list(weights)
        bounds = np.cumsum(list(weights.values()))
        return options[
            min(int(np.searchsorted(bounds, fraction * bounds[-1], side="right")), len(options) - 1)
        ]

    def chance(self, probability: float) -> bool:
        """Return True with the given probability."""
        return bool(self.rng.random() < probability)

    def uniform(self, low: float, high: float) -> float:
        """Return a uniform draw."""
        return float(self.rng.uniform(low, high))


@dataclass(eq=False)
class SceneDraft:
    """A scene in the local frame of its map, before the excerpt and the global transform."""

    road_map: RoadMap
    ego: EgoMotion
    tracks: list[Track]
    route: list[str]
    command: str
    traffic_lights: list[tuple[str, bool]] = field(default_factory=list)
    info: dict[str, object] = field(default_factory=dict)


def ego_initial_speed(dice: Dice) -> tuple[str, float]:
    """Return the ego's speed class and its speed at the current frame."""
    speed_class = dice.pick("ego_speed", {"standstill": 0.25, "slow": 0.15, "medium": 0.35, "fast": 0.25})
    low, high = EGO_SPEED_CLASSES[speed_class]
    return speed_class, dice.uniform(low, high) if high > 0 else 0.0


def free_speed(dice: Dice, speed: float) -> Transition:
    """Return a plausible free-driving speed profile from `speed`: cruising with a gentle change, or starting off."""
    if speed <= 0.0:
        if dice.chance(0.45):
            go = dice.uniform(0.2, 2.0)
            target = dice.uniform(3.0, 8.0)
            return Transition(0.0, target, go, go + 1.5 * target / dice.uniform(1.2, 2.5))
        return Transition.constant(0.0)
    target = float(np.clip(speed + dice.rng.normal(0.0, 1.5), 0.6 * speed, 22.0))
    start = dice.uniform(-1.5, 2.0)
    return Transition(speed, target, start, start + dice.uniform(2.0, 5.0))


def vary_sightings(dice: Dice, tracks: list[Track]) -> list[Track]:
    """Return the tracks with, now and then, one seen in a single frame and one seen only in the history.

    The first track (the lead, when there is one) keeps every sighting.
    """
    tracks = list(tracks)
    if len(tracks) > 1 and dice.pick("single_frame", {True: 0.5, False: 0.5}):
        index = int(dice.rng.integers(1, len(tracks)))
        tracks[index] = seen_once(dice.rng, tracks[index])
    if len(tracks) > 1 and dice.chance(0.2):
        index = int(dice.rng.integers(1, len(tracks)))
        tracks[index] = seen_in_history_only(tracks[index])
    return tracks


def lead_plan(
    dice: Dice, behaviour: str, speed: float, path: Polyline, s0: float
) -> tuple[Transition, Track | None]:
    """Return the ego's speed profile and a lead vehicle ahead of it on `path` (None when free).

    Behaviours: none, cruise, brake (the lead brakes and the ego follows suit), stopped (a standing
    lead the ego stops behind; with a standing ego, a queue that may move off).
    """
    if behaviour == "none":
        return free_speed(dice, speed), None
    size = vehicle_size(dice.rng)
    if behaviour == "stopped" and speed <= 0.0:  # a queue: both wait, or both move off
        ego_speed = lead_speed = Transition.constant(0.0)
        if dice.chance(0.4):
            go, target = dice.uniform(0.0, 1.5), dice.uniform(3.0, 6.0)
            duration = 1.5 * target / dice.uniform(1.2, 2.2)
            lead_speed = Transition(0.0, target, go, go + duration)
            go += dice.uniform(0.6, 1.4)
            ego_speed = Transition(0.0, target, go, go + duration)
        margin = dice.uniform(2.0, 6.0)
    elif behaviour == "stopped":
        ego_speed = braking(speed, dice.uniform(1.5, 3.5), dice.uniform(0.0, 0.8))
        lead_speed = Transition.constant(0.0)
        margin = ego_speed.distance_until_settled() + dice.uniform(2.5, 6.0)
    elif behaviour == "cruise":
        lead = max(1.0, speed + dice.uniform(-2.0, 2.0))
        start = dice.uniform(-1.5, 3.0)
        lead_speed = Transition(
            lead, max(0.5, lead + dice.uniform(-1.5, 1.5)), start, start + dice.uniform(2.0, 4.0)
        )
        start = dice.uniform(-1.0, 1.0)
        ego_speed = Transition(
            speed, max(0.0, lead + dice.uniform(-1.0, 0.5)), start, start + dice.uniform(2.0, 4.0)
        )
        margin = max(5.0, speed * dice.uniform(0.8, 2.0))
    else:  # brake
        lead = max(2.0, speed + dice.uniform(-1.0, 1.0))
        final, start = lead * dice.uniform(0.0, 0.5), dice.uniform(0.0, 1.5)
        # A smoothstep from v to w over d seconds peaks at 1.5 |v - w| / d.
        duration = max(1.0, 1.5 * (lead - final) / dice.uniform(2.0, 4.0))
        lead_speed = Transition(lead, final, start, start + duration)
        start += dice.uniform(0.4, 1.0)
        ego_speed = Transition(
            speed, final * dice.uniform(0.6, 1.0), start, start + duration * dice.uniform(1.0, 1.3)
        )
        margin = max(6.0, speed * dice.uniform(1.0, 1.8))
    lead_s0 = s0 + EGO_FRONT_LENGTH + margin + size[0] / 2
    ego_s = s0 + ego_speed.integral(FRAME_TIMES)
    lead_s0 += max(0.0, MIN_GAP - gap_ahead(ego_s, lead_s0 + lead_speed.integral(FRAME_TIMES), size[0]))
    return ego_speed, moving_track("vehicle", size, path, lead_s0, lead_speed)
