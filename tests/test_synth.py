"""Synthetic split generator: valid scenes, the same bytes for a seed, and coverage of what the metrics need."""

from __future__ import annotations

import itertools
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import shapely

from scorer.geometry import EGO_HALF_LENGTH, EGO_HALF_WIDTH, box_corners, ego_center
from scorer.scene import CATEGORIES, FUTURE_FRAMES, STATIC_CATEGORIES, Frame, Scene, iter_scenes
from scorer.synth import GENERATOR_VERSION, synthesize_scene, synthesize_split
from scorer.synth.corridor import corridor_scene
from scorer.synth.draft import Dice
from scorer.synth.export import EXCERPT_HALF_SIDE, Placement, map_excerpt
from scorer.synth.intersection import intersection_scene

SEED = 20261122
N_SCENES = 60


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "synthetic_split"
    synthesize_split(out, N_SCENES, SEED)
    return out


@pytest.fixture(scope="module")
def scenes(split: Path) -> list[Scene]:
    return list(iter_scenes(split))


@pytest.fixture(scope="module")
def notes(split: Path) -> dict[str, dict[str, object]]:
    return {note["token"]: note for note in json.loads((split / "split.json").read_text())["scenes"]}


def _ego_frame(frame: Frame, xy: np.ndarray) -> np.ndarray:
    """Return global points (..., 2) in the ego frame of `frame` (rear axle at the origin, x forward)."""
    ego = frame.ego
    c, s = np.cos(ego.heading), np.sin(ego.heading)
    d = xy - [ego.x, ego.y]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def _ego_box(frame: Frame) -> shapely.Polygon:
    x, y = ego_center(frame.ego.x, frame.ego.y, frame.ego.heading)
    return shapely.Polygon(box_corners(x, y, frame.ego.heading, EGO_HALF_LENGTH, EGO_HALF_WIDTH))


def _object_boxes(frame: Frame) -> np.ndarray:
    b = frame.boxes
    return shapely.polygons(box_corners(b[:, 0], b[:, 1], b[:, 6], b[:, 3] / 2, b[:, 4] / 2))


def _count(scenes: list[Scene], predicate: Callable[[Scene], bool]) -> int:
    return sum(bool(predicate(scene)) for scene in scenes)


# --- files and determinism ------------------------------------------------------------------------------------


def test_every_scene_loads_and_the_split_is_described(split: Path, scenes: list[Scene]) -> None:
    tokens = sorted(path.name.removesuffix(".json.gz") for path in (split / "scenes").iterdir())
    assert len(scenes) == N_SCENES and [scene.token for scene in scenes] == tokens
    assert all(len(token) == 16 and int(token, 16) >= 0 for token in tokens)
    metadata = json.loads((split / "split.json").read_text())
    assert (metadata["name"], metadata["seed"], metadata["n"]) == ("synthetic_split", SEED, N_SCENES)
    assert metadata["generator_version"] == GENERATOR_VERSION
    assert sorted(note["token"] for note in metadata["scenes"]) == tokens
    for scene in scenes:
        assert (scene.current_index, len(scene.frames), scene.frame_interval_s) == (3, 14, 0.5)
        assert np.all(np.diff([frame.timestamp_us for frame in scene.frames]) == 500_000)


def test_same_seed_same_bytes_and_scenes_depend_on_seed_and_index_only(tmp_path: Path) -> None:
    calls: list[int] = []
    first = synthesize_split(tmp_path / "a" / "split", 8, 5, progress=calls.append)
    second = synthesize_split(tmp_path / "b" / "split", 8, 5)
    assert first == second and calls == [1] * 8
    for name in ["split.json", *(f"scenes/{token}.json.gz" for token in first)]:
        assert (tmp_path / "a" / "split" / name).read_bytes() == (
            tmp_path / "b" / "split" / name
        ).read_bytes(), name
    token, content, _ = synthesize_scene(5, 6)
    assert (
        token == first[6]
        and content == (tmp_path / "a" / "split" / "scenes" / f"{token}.json.gz").read_bytes()
    )
    assert not set(synthesize_split(tmp_path / "c", 8, 6)) & set(first)


def test_refuses_to_mix_with_an_existing_split(tmp_path: Path) -> None:
    synthesize_split(tmp_path / "split", 1, 0)
    with pytest.raises(FileExistsError, match="not empty"):
        synthesize_split(tmp_path / "split", 1, 0)


# --- map --------------------------------------------------------------------------------------------------------


def test_maps_are_utm_like_and_baselines_dense(scenes: list[Scene]) -> None:
    for scene in scenes:
        lanes = scene.map.lanes + scene.map.lane_connectors
        vertices = np.concatenate([lane.baseline for lane in lanes])
        assert np.all(np.abs(vertices) > 1e5), scene.token
        spacing = np.concatenate([np.hypot(*np.diff(lane.baseline, axis=0).T) for lane in lanes])
        assert spacing.max() <= 2.3 and spacing.min() > 0.05, (
            scene.token
        )  # 2 m, longer on the outside of curves
        assert all(lane.polygon.is_valid for lane in lanes), scene.token


def test_two_way_roads_have_multi_lane_roadblocks_beside_oncoming_ones(scenes: list[Scene]) -> None:
    def oncoming_pair(scene: Scene) -> bool:
        lanes = {lane.id: lane for lane in scene.map.lanes}
        for block in scene.map.roadblocks:
            if len(block.lanes) < 2:
                continue
            forward = lanes[block.lanes[0]].baseline
            direction = forward[-1] - forward[0]
            for other in scene.map.roadblocks:
                if other is block or not other.polygon.touches(block.polygon) or not other.lanes:
                    continue
                opposite = lanes[other.lanes[0]].baseline
                if np.dot(direction, opposite[-1] - opposite[0]) < -0.9 * np.hypot(*direction) * np.hypot(
                    *(opposite[-1] - opposite[0])
                ):
                    return True
        return False

    assert _count(scenes, oncoming_pair) >= 10


def test_every_kind_of_road_is_present(scenes: list[Scene], notes: dict[str, dict[str, object]]) -> None:
    def kind(name: str) -> list[Scene]:
        return [scene for scene in scenes if notes[scene.token]["kind"] == name]

    for name in ("straight", "curve", "intersection", "carpark", "carpark_start"):
        assert len(kind(name)) >= 3, name
    for scene in kind("intersection"):
        assert scene.map.intersections and scene.current_frame.traffic_lights
        connector_lanes = {lane.id for lane in scene.map.lane_connectors}
        assert {lane for lane, _ in scene.current_frame.traffic_lights} <= connector_lanes
    for scene in kind("carpark") + kind("carpark_start"):
        assert scene.map.carpark_areas
    for scene in kind("carpark_start"):
        ego = scene.current_frame.ego
        assert ego.vx == 0.0 and any(
            area.polygon.contains(_ego_box(scene.current_frame)) for area in scene.map.carpark_areas
        )

    def turning(scene: Scene) -> float:
        route = set(scene.current_frame.route_roadblocks)
        headings = [
            np.unwrap(np.arctan2(*np.diff(lane.baseline, axis=0)[:, ::-1].T))
            for lane in scene.map.lanes
            if lane.roadblock in route
        ]
        return max(float(np.ptp(h)) for h in headings)

    assert all(turning(scene) < 0.005 for scene in kind("straight"))  # millimetre rounding only
    assert all(turning(scene) > 0.05 for scene in kind("curve"))


def test_map_excerpt_follows_the_square_and_route_rule() -> None:
    for index, draft in enumerate(
        [
            corridor_scene(Dice(np.random.default_rng(3), {}), "curve", 5000),
            intersection_scene(Dice(np.random.default_rng(4), {"route_variant": 0.0}), 7000),
        ]
    ):
        placement = Placement(0.7 + index, 331_000.0, 4_691_000.0)
        x, y, heading = draft.ego.poses[3]
        centre = placement.points(np.array(ego_center(x, y, heading)))
        excerpt = map_excerpt(draft, placement, centre)
        square = shapely.box(*(centre - EXCERPT_HALF_SIDE), *(centre + EXCERPT_HALF_SIDE))
        road_map = draft.road_map
        ids = {layer: {item["id"] for item in items} for layer, items in excerpt.items()}
        far = 0
        for layer in ("roadblocks", "roadblock_connectors", *road_map.areas):
            for item in (
                getattr(road_map, layer)
                if layer in ("roadblocks", "roadblock_connectors")
                else road_map.areas[layer]
            ):
                touching = shapely.Polygon(np.round(placement.points(item.polygon), 3)).intersects(square)
                if touching:
                    assert item.id in ids[layer], (layer, item.id)
                elif layer in ("roadblocks", "roadblock_connectors"):
                    far += item.id in ids[layer]
                else:
                    assert item.id not in ids[layer]
        blocks = {b.id: b for b in road_map.roadblocks + road_map.roadblock_connectors}
        assert set(draft.route) <= ids["roadblocks"] | ids["roadblock_connectors"]
        for start in draft.route:  # 30 roadblock steps forward, 15 backward (a step: roadblock + connector)
            for direction, steps in (("outgoing", 60), ("incoming", 30)):
                frontier = {start}
                for _ in range(steps):
                    frontier = {n for b in frontier for n in getattr(blocks[b], direction)}
                    assert frontier <= ids["roadblocks"] | ids["roadblock_connectors"]
        kept_blocks = ids["roadblocks"] | ids["roadblock_connectors"]
        for layer in ("lanes", "lane_connectors"):
            members = {lane.id for lane in getattr(road_map, layer) if lane.block in kept_blocks}
            assert ids[layer] == members
        assert far > 0  # the route neighbourhood reaches beyond the square


# --- route ------------------------------------------------------------------------------------------------------


def _block_at_ego(scene: Scene) -> str | None:
    ego = scene.current_frame.ego
    point = shapely.Point(ego.x, ego.y)
    for block in scene.map.roadblocks + scene.map.roadblock_connectors:
        if block.polygon.intersects(point.buffer(0.01)):
            return block.id
    return None


def test_every_scene_has_a_drivable_route(scenes: list[Scene], notes: dict[str, dict[str, object]]) -> None:
    variants: set[str] = set()
    for scene in scenes:
        route = scene.current_frame.route_roadblocks
        blocks = {b.id: b for b in scene.map.roadblocks + scene.map.roadblock_connectors}
        assert route and set(route) <= set(blocks), scene.token
        for before, after in itertools.pairwise(route):
            joined = after in blocks[before].outgoing
            bridged = any(after in blocks[c].outgoing for c in blocks[before].outgoing if c in blocks)
            assert joined or bridged, (scene.token, before, after)
            variants.add("missing_connector" if not joined else "")
        lengths = {
            lane.roadblock: float(np.sum(np.hypot(*np.diff(lane.baseline, axis=0).T)))
            for lane in scene.map.lanes + scene.map.lane_connectors
        }
        assert sum(lengths.get(block, 0.0) for block in route) > 120.0, scene.token
        start = _block_at_ego(scene)
        if notes[scene.token]["kind"] == "carpark_start":
            assert start is None  # parked off the road: the engine takes the nearest roadblock
            continue
        assert start is not None, scene.token
        if start in route:
            variants.add("with_previous" if route.index(start) > 0 else "normal")
        else:
            variants.add("starts_ahead")
            reachable = set(blocks[start].outgoing) | {
                n for c in blocks[start].outgoing if c in blocks for n in blocks[c].outgoing
            }
            assert route[0] in reachable, scene.token
    assert {"normal", "with_previous", "starts_ahead", "missing_connector"} <= variants


# --- objects and the ego ----------------------------------------------------------------------------------------


def test_objects_have_realistic_boxes_and_static_ones_stand_still(scenes: list[Scene]) -> None:
    limits = {
        "vehicle": (3.5, 13.0),
        "pedestrian": (0.3, 1.0),
        "bicycle": (1.4, 2.0),
        "traffic_cone": (0.2, 0.6),
        "barrier": (0.8, 2.6),
    }
    for scene in scenes:
        for frame in scene.frames:
            for category, box, velocity in zip(frame.categories, frame.boxes, frame.velocities, strict=True):
                low, high = limits.get(category, (0.1, 1.5))
                assert low <= box[3] <= high and 0.1 <= box[4] <= 2.7, (scene.token, category, box)
                if category in STATIC_CATEGORIES:
                    assert not np.any(velocity), (scene.token, category)


def test_every_object_category_and_road_user_is_present(scenes: list[Scene]) -> None:
    seen_categories: set[str] = set()
    found = dict.fromkeys(
        ["lead", "adjacent", "oncoming", "stopped", "crossing", "cyclist", "single_frame"], 0
    )
    for scene in scenes:
        current = scene.current_frame
        horizon = scene.future_frames
        for frame in horizon:
            seen_categories.update(frame.categories)
        sightings: dict[str, int] = {}
        for frame in horizon:
            for track in frame.tracks:
                sightings[track] = sightings.get(track, 0) + 1
        found["single_frame"] += any(count == 1 for count in sightings.values())
        local = _ego_frame(current, current.boxes[:, :2])
        heading = current.ego.heading
        for category, (x, y), box, velocity in zip(
            current.categories, local, current.boxes, current.velocities, strict=True
        ):
            speed = np.hypot(*velocity)
            along = np.cos(box[6] - heading)
            if category == "vehicle":
                found["lead"] += 3.0 < x < 60.0 and abs(y) < 1.0 and along > 0.95
                found["adjacent"] += abs(x) < 40.0 and 2.5 < abs(y) < 8.0 and along > 0.95 and speed > 1.0
                found["oncoming"] += abs(x) < 80.0 and along < -0.95 and speed > 1.0
                found["stopped"] += speed == 0.0
            found["crossing"] += (
                category == "pedestrian"
                and speed > 0.8
                and abs(np.dot(velocity / max(speed, 1e-9), [np.cos(heading), np.sin(heading)])) < 0.5
            )
            found["cyclist"] += category == "bicycle" and speed > 1.0
    assert seen_categories == set(CATEGORIES)
    assert all(count >= 3 for count in found.values()), found


def test_red_lights_on_the_ego_connector_and_ego_speeds(scenes: list[Scene]) -> None:
    def ego_connector_light(scene: Scene) -> set[bool]:
        route = set(scene.current_frame.route_roadblocks)
        lights = dict(scene.current_frame.traffic_lights)
        return {
            lights[lane.id]
            for lane in scene.map.lane_connectors
            if lane.roadblock in route and lane.id in lights
        }

    assert _count(scenes, lambda s: True in ego_connector_light(s)) >= 5
    assert _count(scenes, lambda s: False in ego_connector_light(s)) >= 5
    speeds = np.array([scene.current_frame.ego.vx for scene in scenes])
    assert (
        np.sum(speeds == 0.0) >= 8
        and np.sum(speeds >= 15.0) >= 3
        and np.sum((speeds > 3) & (speeds < 12)) >= 10
    )


def _lane_at(scene: Scene, frame: Frame) -> str | None:
    point = shapely.Point(frame.ego.x, frame.ego.y)
    return next((lane.id for lane in scene.map.lanes if lane.polygon.contains(point)), None)


def test_some_egos_change_lanes(scenes: list[Scene]) -> None:
    def changes_lane(scene: Scene) -> bool:
        start, end = _lane_at(scene, scene.current_frame), _lane_at(scene, scene.frames[-1])
        if start is None or end is None:
            return False
        successors = {lane.id: lane.outgoing for lane in scene.map.lanes + scene.map.lane_connectors}
        reachable = {start}
        for _ in range(8):  # lanes and lane connectors alternate along a road
            reachable |= {n for lane in reachable for n in successors.get(lane, ())}
        return end not in reachable

    assert _count(scenes, changes_lane) >= 2


def test_human_futures_are_plausible(scenes: list[Scene]) -> None:
    for scene in scenes:
        drivable = shapely.union_all(
            [p.polygon for p in scene.map.roadblocks + scene.map.intersections + scene.map.carpark_areas]
        )
        frames = scene.frames[scene.current_index :]
        horizon_tracks = {track for frame in scene.future_frames for track in frame.tracks}
        once = {t for t in horizon_tracks if sum(t in f.tracks for f in scene.future_frames) == 1}
        standing = [
            poly
            for frame in scene.future_frames
            for track, poly in zip(frame.tracks, _object_boxes(frame), strict=True)
            if track in once
        ]
        for frame in frames[: FUTURE_FRAMES + 1]:
            ego_box = _ego_box(frame)
            assert not shapely.intersects(ego_box, _object_boxes(frame)).any(), (scene.token, frame.token)
            assert not any(ego_box.intersects(poly) for poly in standing), scene.token
            corners = np.asarray(ego_box.exterior.coords)[:4]
            assert shapely.contains_xy(drivable, corners[:, 0], corners[:, 1]).all(), (
                scene.token,
                frame.token,
            )
        x = np.array([[f.ego.x, f.ego.y] for f in frames])
        steps = np.hypot(*np.diff(x, axis=0).T)
        mean_speed = 0.25 * np.add([f.ego.vx for f in frames[:-1]], [f.ego.vx for f in frames[1:]])
        assert np.allclose(steps, mean_speed, atol=0.3), scene.token
        assert all(abs(f.ego.ax) <= 4.5 and abs(f.ego.ay) <= 4.0 and f.ego.vx >= 0.0 for f in frames), (
            scene.token
        )
        moving = steps > 0.5
        motion_heading = np.arctan2(*np.diff(x, axis=0)[:, ::-1].T)
        heading = np.array([f.ego.heading for f in frames[:-1]])
        assert np.all(np.abs(np.sin(motion_heading - heading)[moving]) < 0.2), scene.token
