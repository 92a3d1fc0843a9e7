"""PDM-Closed's forecast observation (spec 9.3) on a reference scene with hand-placed objects."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import shapely

from scorer.drivable_map import DrivableMap
from scorer.geometry import ego_center
from scorer.pdm_closed import PROPOSAL_STEPS, ego_polygons, plan_scene, unroll_proposals
from scorer.planner_observation import observe_for_planner, scoring_observation
from scorer.scene import Frame, Lane, Scene, load_scene

SCENE = Path(__file__).parent / "fixtures" / "reference" / "scenes" / "05ef979906eefe4a.json.gz"


def _scene_with(objects: list[tuple[str, str, list[float], list[float]]], lights: tuple = ()) -> Scene:
    """The reference scene with the current frame's objects replaced by (track, category, box, velocity)."""
    scene = load_scene(SCENE)
    frame = scene.current_frame
    replaced = frame._replace(
        tracks=tuple(track for track, _, _, _ in objects),
        categories=tuple(category for _, category, _, _ in objects),
        boxes=np.array([box for _, _, box, _ in objects], dtype=np.float64).reshape(-1, 7),
        velocities=np.array([velocity for _, _, _, velocity in objects], dtype=np.float64).reshape(-1, 2),
        traffic_lights=lights,
    )
    frames = list(scene.frames)
    frames[scene.current_index] = replaced
    return scene._replace(frames=tuple(frames))


def _ahead(scene: Scene, distance: float, lateral: float = 0.0) -> tuple[float, float, float]:
    """A point `distance` m ahead of (and `lateral` m left of) the ego centre, with the ego heading."""
    ego = scene.current_frame.ego
    cx, cy = ego_center(ego.x, ego.y, ego.heading)
    return (
        float(cx + distance * math.cos(ego.heading) - lateral * math.sin(ego.heading)),
        float(cy + distance * math.sin(ego.heading) + lateral * math.cos(ego.heading)),
        ego.heading,
    )


def _footprint(frame: Frame) -> shapely.Polygon:
    return ego_polygons(np.array([[frame.ego.x, frame.ego.y, frame.ego.heading]]))[0]


def _observe(scene: Scene, route_lanes: dict[str, Lane] | None = None):
    return observe_for_planner(scene, route_lanes or {}, _footprint(scene.current_frame))


def _box(x: float, y: float, heading: float, length: float = 4.0, width: float = 2.0) -> list[float]:
    return [x, y, 0.0, length, width, 1.5, heading]


def test_order_is_static_then_vehicles_pedestrians_bicycles_each_nearest_first_within_100_m() -> None:
    base = load_scene(SCENE)
    objects = [
        ("bike", "bicycle", _box(*_ahead(base, 30.0)), [0.0, 0.0]),
        ("far_car", "vehicle", _box(*_ahead(base, 60.0)), [0.0, 0.0]),
        ("cone", "traffic_cone", _box(*_ahead(base, 50.0, 3.0)), [0.0, 0.0]),
        ("walker", "pedestrian", _box(*_ahead(base, 20.0, 5.0)), [0.0, 0.0]),
        ("near_car", "vehicle", _box(*_ahead(base, 15.0)), [0.0, 0.0]),
        ("too_far", "vehicle", _box(*_ahead(base, 100.5)), [0.0, 0.0]),
    ]
    observation = _observe(_scene_with(objects))
    assert observation.tokens == ("cone", "near_car", "far_car", "walker", "bike")
    assert observation.polygons.shape == (26, 5)
    assert observation.is_agent.tolist() == [False, True, True, True, True]


def test_agents_move_at_constant_velocity_along_their_heading_or_against_it() -> None:
    base = load_scene(SCENE)
    x, y, heading = _ahead(base, 20.0)
    speed = 5.0
    forward = [speed * math.cos(heading), speed * math.sin(heading)]
    objects = [
        ("forward", "vehicle", _box(x, y, heading), forward),
        ("reversing", "vehicle", _box(x, y, heading), [-forward[0], -forward[1]]),
        ("cone", "traffic_cone", _box(x, y, heading), forward),  # static: velocity ignored
    ]
    observation = _observe(_scene_with(objects))
    index = {token: i for i, token in enumerate(observation.tokens)}
    for token, sign in (("forward", 1.0), ("reversing", -1.0), ("cone", 0.0)):
        start = np.array(observation.polygons[0, index[token]].centroid.coords[0])
        later = np.array(observation.polygons[25, index[token]].centroid.coords[0])  # sample 50: 5 s
        shift = sign * 5.0 * speed * np.array([math.cos(heading), math.sin(heading)])
        assert np.allclose(later - start, shift, atol=1e-6), token
    assert observation.speeds[index["reversing"]] == speed and observation.speeds[index["cone"]] == 0.0


def test_red_route_connectors_are_obstacles_and_contained_or_touching_tokens_are_collided() -> None:
    base = load_scene(SCENE)
    connectors = {lane.id: lane for lane in base.map.lane_connectors}
    on_route = {key: connectors[key] for key in ("303274", "303280")}
    ego = base.current_frame.ego
    cx, cy = ego_center(ego.x, ego.y, ego.heading)
    objects = [
        ("touching", "vehicle", _box(float(cx), float(cy), ego.heading + 0.3), [0.0, 0.0]),
        ("ahead", "barrier", _box(*_ahead(base, 25.0)), [0.0, 0.0]),
    ]
    lights = (("303274", True), ("303280", False), ("303021", True))  # green, and red but off route
    observation = _observe(_scene_with(objects, lights), on_route)
    assert observation.tokens == ("ahead", "touching", "red_light_303274")
    assert observation.polygons[7, 2] is connectors["303274"].polygon
    assert observation.collided.tolist() == [False, True, False]
    assert observation.is_red_light.tolist() == [False, False, True]

    # A red light counts as collided only when it contains the whole ego footprint.
    huge = dataclasses.replace(connectors["303274"], polygon=shapely.buffer(shapely.Point(cx, cy), 20.0))
    observation = _observe(_scene_with(objects, (("303274", True),)), {"303274": huge})
    assert observation.collided.tolist() == [False, True, True]


def test_the_scoring_view_has_51_steps_reading_map_k_half_and_leaves_out_collided_and_red_lights() -> None:
    base = load_scene(SCENE)
    ego = base.current_frame.ego
    cx, cy = ego_center(ego.x, ego.y, ego.heading)
    objects = [
        ("touching", "vehicle", _box(float(cx), float(cy), ego.heading), [1.0, 0.0]),
        ("ahead", "vehicle", _box(*_ahead(base, 25.0)), [3.0, 4.0]),
        ("cone", "traffic_cone", _box(*_ahead(base, 40.0)), [0.0, 0.0]),
    ]
    connectors = {lane.id: lane for lane in base.map.lane_connectors}
    observation = _observe(_scene_with(objects, (("303274", True),)), {"303274": connectors["303274"]})
    scoring = scoring_observation(observation)
    assert scoring.tokens == ("cone", "ahead")
    assert scoring.object_types == ("TRAFFIC_CONE", "VEHICLE")
    assert scoring.is_agent.tolist() == [False, True] and scoring.first_speed.tolist() == [0.0, 5.0]
    assert scoring.present.shape == (51, 2) and scoring.present.all()
    for k in (0, 1, 2, 7, 49, 50):
        assert shapely.equals_exact(scoring.polygons[k, 1], observation.polygons[k // 2, 2], tolerance=0.0)


def test_without_objects_or_map_polygons_the_proposals_drive_free() -> None:
    scene = _scene_with([])
    no_map = DrivableMap(tokens=(), types=(), built=np.empty(0, dtype=object))
    proposals = unroll_proposals([plan_scene(scene, no_map)])
    targets = proposals.plans[0].targets
    speeds = proposals.unroll.idm[:, PROPOSAL_STEPS, 1].reshape(3, 5)
    reachable = scene.current_frame.ego.vx + 1.5 * 4.0  # a_max over the 4 s
    # Each policy heads for its own target, limited by a_max; the three paths agree.
    assert np.all(speeds <= np.minimum(targets, reachable) + 1e-9)
    assert np.all(np.abs(speeds[:, 0] - targets[0]) < 0.01)
    assert np.all(np.diff(speeds, axis=1) >= 0)
    assert np.allclose(speeds, speeds[0], rtol=1e-6)
