"""PDM-Closed's own view of the world: a constant-velocity forecast of the current frame.

Unlike the evaluation observation (recorded future, `scorer.observation`), the planner sees only the
current frame's objects within 100 m of the ego centre (the nearest 50 vehicles, 25 pedestrians,
10 bicycles and 50 static objects), agents moving straight at constant speed, plus the polygons of
red lane connectors on the route. Forecast maps exist at samples 0, 2, ..., 50 (0.1 s each); time
index k reads map k // 2. Map order: static objects, agents, red lights (as `PDMObservation`;
docs/engine.md, "Observation and forecasts: PDM-Closed's forecast").

Per-scene isolation: the devkit's planner keeps a running list of "collided" tokens (objects the ego
overlaps at t0, red lights that contain it) across all scenes of a caching worker, so a later scene
can ignore objects of an earlier one. Here the list starts empty for every scene, as in the reference
run, and holds only this scene's own t0 overlaps
(docs/engine.md, "Observation and forecasts: the collided list").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import shapely

from scorer.geometry import (
    BoolArray,
    FloatArray,
    IntArray,
    arctan2_avx512,
    box_corners,
    ego_center,
    normalize_angle,
)
from scorer.observation import Observation
from scorer.red_lights import RED_LIGHT_TOKEN, RedLights, red_lanes
from scorer.scene import AGENT_CATEGORIES, Lane, Scene

MAP_RADIUS = 100.0  # objects farther than this from the ego centre are not seen (Euclidean)
MAX_AGENTS = {"vehicle": 50, "pedestrian": 25, "bicycle": 10}  # nearest kept per type, in this order
MAX_STATIC_OBJECTS = 50
FORECAST_SAMPLES = np.arange(0, 52, 2)  # samples 0, 2, ..., 50 at 0.1 s
SAMPLE_INTERVAL_S = 0.1
SCORING_STEPS = 51  # time indices 0..50 of the planner's scoring observation


@dataclass(frozen=True, eq=False)
class PlannerObservation:
    """Forecast maps in the devkit's object order, with what the leading-agent search reads per object."""

    tokens: tuple[str, ...]  # n objects: static objects, agents, red lights
    categories: tuple[str, ...]  # scene category, "red_light" for red lights
    is_agent: BoolArray  # (n,)
    is_red_light: BoolArray  # (n,) token contains "red_light" (the devkit's test)
    speeds: FloatArray  # (n,) |velocity| of the current-frame object (0 for static objects and red lights)
    headings: FloatArray  # (n,) box heading (0 for red lights)
    collided: BoolArray  # (n,) overlaps the ego footprint at t0 (red lights: contain it); ignored throughout
    polygons: npt.NDArray[np.object_]  # (26, n) forecast map j = sample 2j
    corners: FloatArray  # (26, n, 4, 2) the boxes' ring corners FL, RL, RR, FR in each map (NaN: red lights)
    trees: tuple[shapely.STRtree, ...]  # per forecast map, node capacity 10 (query order = the devkit's)
    red_lights: RedLights  # the red lights of the maps, at every time index (v2's TLC reads them)

    @staticmethod
    def map_index(time_index: int) -> int:
        """Return the forecast map read at 10 Hz time index `time_index`."""
        return time_index // 2


def _nearest_first(distances: FloatArray, limit: int) -> IntArray:
    # The devkit's np.argsort (default kind), then the first `limit`.
    return np.argsort(distances)[:limit]


def observe_for_planner(
    scene: Scene, route_lanes: Mapping[str, Lane], footprint: shapely.Polygon
) -> PlannerObservation:
    """Return PDM-Closed's forecast observation of the current frame (`PDMObservation.update`).

    See docs/engine.md, "Observation and forecasts: PDM-Closed's forecast".
    """
    frame = scene.current_frame
    center = np.array(ego_center(frame.ego.x, frame.ego.y, frame.ego.heading))
    boxes, velocities = frame.boxes, frame.velocities
    categories = np.array(frame.categories, dtype=object)
    seen = np.hypot(center[0] - boxes[:, 0], center[1] - boxes[:, 1]) <= MAP_RADIUS
    corners = box_corners(boxes[:, 0], boxes[:, 1], boxes[:, 6], boxes[:, 3] / 2.0, boxes[:, 4] / 2.0)
    # Ring FL, RL, RR, FR, FL: the devkit overwrites the centre slot of its 5-point box with FL.
    rings = np.concatenate([corners, corners[:, :1]], axis=1)
    center_distances = ((boxes[:, :2] - center) ** 2.0).sum(axis=-1) ** 0.5

    def nearest(mask: BoolArray, limit: int) -> IntArray:
        members = np.flatnonzero(mask)
        return members[_nearest_first(center_distances[members], limit)]

    is_agent_category = np.isin(categories, AGENT_CATEGORIES)
    static = nearest(seen & ~is_agent_category, MAX_STATIC_OBJECTS)
    agents = np.concatenate(
        [nearest(seen & (categories == category), limit) for category, limit in MAX_AGENTS.items()]
    ).astype(np.intp)

    speeds = np.hypot(velocities[:, 0], velocities[:, 1])
    headings = boxes[:, 6]
    # Agents move along their heading, or against it when they drive backwards. The devkit wraps every
    # object's angles; only the kept agents' are read, so only theirs are (the arctan2 replay costs per angle).
    agent_headings, agent_speeds = headings[agents], speeds[agents]
    agent_motion = arctan2_avx512(velocities[agents, 1], velocities[agents, 0])
    forward = np.abs(normalize_angle(agent_headings - agent_motion)) < np.pi / 2
    track_headings = np.where(forward, agent_headings, normalize_angle(agent_headings + np.pi))
    agent_velocity = np.stack(
        [np.cos(track_headings) * agent_speeds, np.sin(track_headings) * agent_speeds], axis=-1
    )

    red_lights = RedLights.constant(red_lanes(frame.traffic_lights, route_lanes), SCORING_STEPS)
    light_polygons = red_lights.polygons

    # Every map's boxes at once: agents moved by delta_t * velocity, static objects where they stand.
    delta_t = FORECAST_SAMPLES * SAMPLE_INTERVAL_S
    box_rings = np.concatenate(
        [
            np.broadcast_to(rings[static], (len(FORECAST_SAMPLES), *rings[static].shape)),
            rings[agents] + delta_t[:, None, None, None] * agent_velocity[:, None],
        ],
        axis=1,
    )
    boxes_end = len(static) + len(agents)
    maps = np.empty((len(FORECAST_SAMPLES), boxes_end + len(light_polygons)), dtype=object)
    maps[:, : len(static)] = shapely.polygons(rings[static])  # the same objects in every map
    maps[:, len(static) : boxes_end] = shapely.polygons(box_rings[:, len(static) :])
    maps[:, boxes_end:] = light_polygons
    corners = np.full((*maps.shape, 4, 2), np.nan)
    corners[:, :boxes_end] = box_rings[..., :4, :]
    trees = tuple(shapely.STRtree(polygons, node_capacity=10) for polygons in maps)

    tokens = tuple(frame.tracks[i] for i in static) + tuple(frame.tracks[i] for i in agents)
    tokens += red_lights.tokens
    is_red_light = np.array([RED_LIGHT_TOKEN in token for token in tokens], dtype=bool)
    objects = np.concatenate([static, agents]).astype(np.intp)
    touching = np.zeros(len(tokens), dtype=bool)
    touching[trees[0].query(footprint, predicate="intersects")] = True
    # A red light counts only when it contains the whole ego; an object when it touches it.
    collided = touching & (~is_red_light | shapely.within(footprint, maps[0]))
    pad = np.zeros(len(light_polygons))
    return PlannerObservation(
        tokens=tokens,
        categories=tuple(frame.categories[i] for i in objects) + (RED_LIGHT_TOKEN,) * len(light_polygons),
        is_agent=np.concatenate(
            [is_agent_category[objects].astype(bool), np.zeros(len(light_polygons), dtype=bool)]
        ),
        is_red_light=is_red_light,
        speeds=np.concatenate([np.where(is_agent_category, speeds, 0.0)[objects], pad]),
        headings=np.concatenate([headings[objects], pad]),
        collided=collided,
        polygons=maps,
        corners=corners,
        trees=trees,
        red_lights=red_lights,
    )


def scoring_observation(observation: PlannerObservation) -> Observation:
    """Return the planner observation as the scorer reads it: 51 time indices, map k // 2 at index k.

    Collided tokens and red lights are left out of the boxes: NC and TTC skip both before anything else
    (collided tokens seed every proposal's ignore-lists, red lights are skipped by name), so leaving
    them out gives the same scores. The red lights go along apart, for v2's traffic-light compliance,
    which reads no collided list.
    """
    kept = np.flatnonzero(~observation.collided & ~observation.is_red_light)
    time_to_map = np.arange(SCORING_STEPS) // 2
    return Observation(
        tokens=tuple(observation.tokens[i] for i in kept),
        object_types=tuple(observation.categories[i].upper() for i in kept),
        is_agent=observation.is_agent[kept],
        first_speed=observation.speeds[kept],
        present=np.ones((SCORING_STEPS, len(kept)), dtype=bool),
        boxes=observation.corners[time_to_map][:, kept].reshape(-1, 4, 2),  # every box present
        red_lights=observation.red_lights,
    )
