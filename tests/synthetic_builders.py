"""NAVSIM's two-stage data made from scene files, for the two-stage import tests.

A synthetic scene becomes a `Scene.save_to_disk` pickle: 4 frames (annotations in the ego frame, the ego pose
in the global frame) and the future as nuPlan `DetectionsTracks` / `TrafficLightStatuses` (stand-in classes
pickled under nuPlan's module paths, as nuplan-devkit v1.2 pickles them: instance dicts, `(None, slots)` for
`TimePoint`, `StateSE2`, `StateVector2D`, enums as `Enum(value)`); a roll-out pair can also become one 5-frame
pickle (prev2 = frames[:-1], now2 = frames[1:]). Logged frames become an OpenScene log, the map a GeoPackage
(`openscene_builders`). Ego-frame values are the preimages, searched ulp by ulp, that the importer's forward
transform maps back onto the scene's global values exactly, where one exists (`EgoFrameStats` counts).
"""

from __future__ import annotations

import enum
import itertools
import pickle
import sys
import types
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from openscene_builders import exact_yaw_quaternion

from scorer.geometry import normalize_angle, rear_axle_round_trip
from scorer.openscene.frames import EgoPose, boxes_to_global, velocities_to_global
from scorer.scene import AGENT_CATEGORIES, CATEGORIES

SEARCH_ULPS = 6  # the preimage search tries every offset up to this many ulps in each coordinate


# --- nuPlan stand-ins --------------------------------------------------------------------------------------


class _Dict:
    def __init__(self, **state: Any) -> None:
        self.__dict__.update(state)


class _Slots:
    __slots__: tuple[str, ...] = ()

    def __init__(self, **state: Any) -> None:
        for key, value in state.items():
            setattr(self, key, value)


def _stand_in(module: str, name: str, base: type) -> type:
    cls = type(name, (base,), {"__module__": module, "__qualname__": name})
    return cls


STATE = "nuplan.common.actor_state.state_representation"
DetectionsTracks = _stand_in(
    "nuplan.planning.simulation.observation.observation_type", "DetectionsTracks", _Dict
)
TrackedObjects = _stand_in("nuplan.common.actor_state.tracked_objects", "TrackedObjects", _Dict)
Agent = _stand_in("nuplan.common.actor_state.agent", "Agent", _Dict)
StaticObject = _stand_in("nuplan.common.actor_state.static_object", "StaticObject", _Dict)
SceneObjectMetadata = _stand_in("nuplan.common.actor_state.scene_object", "SceneObjectMetadata", _Dict)
OrientedBox = _stand_in("nuplan.common.actor_state.oriented_box", "OrientedBox", _Dict)
TrafficLightStatuses = _stand_in("nuplan.common.maps.maps_datatypes", "TrafficLightStatuses", _Dict)
TrafficLightStatusData = _stand_in("nuplan.common.maps.maps_datatypes", "TrafficLightStatusData", _Dict)


class StateSE2(_Slots):
    __slots__ = ("heading", "x", "y")
    __module__ = STATE


class StateVector2D(_Slots):
    __slots__ = ("_array", "_x", "_y")
    __module__ = STATE


class TimePoint(_Slots):
    __slots__ = ("time_us",)
    __module__ = STATE


class TrackedObjectType(enum.Enum):
    VEHICLE = 0
    PEDESTRIAN = 1
    BICYCLE = 2
    TRAFFIC_CONE = 3
    BARRIER = 4
    CZONE_SIGN = 5
    GENERIC_OBJECT = 6


TrackedObjectType.__module__ = "nuplan.common.actor_state.tracked_objects_types"


class TrafficLightStatusType(enum.IntEnum):
    GREEN = 0
    RED = 2


TrafficLightStatusType.__module__ = "nuplan.common.maps.maps_datatypes"
STAND_INS = (
    DetectionsTracks,
    TrackedObjects,
    Agent,
    StaticObject,
    SceneObjectMetadata,
    OrientedBox,
    TrafficLightStatuses,
    TrafficLightStatusData,
    StateSE2,
    StateVector2D,
    TimePoint,
    TrackedObjectType,
    TrafficLightStatusType,
)


@contextmanager
def nuplan_modules() -> Iterator[None]:
    """Make the stand-ins findable under nuPlan's module paths while pickling."""
    added = []
    for cls in STAND_INS:
        parts = cls.__module__.split(".")
        for depth in range(1, len(parts) + 1):  # pickle imports the module, so its packages too
            name = ".".join(parts[:depth])
            if name not in sys.modules:
                sys.modules[name] = types.ModuleType(name)
                added.append(name)
        setattr(sys.modules[cls.__module__], cls.__name__, cls)
    try:
        yield
    finally:
        for name in added:
            del sys.modules[name]


def write_pickle(path: Path, content: Any) -> None:
    """Pickle as `Scene.save_to_disk` does (HIGHEST_PROTOCOL), nuPlan objects under their module paths."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with nuplan_modules():
        path.write_bytes(pickle.dumps(content, protocol=pickle.HIGHEST_PROTOCOL))


# --- ego-frame preimages -----------------------------------------------------------------------------------


@dataclass
class EgoFrameStats:
    """How many ego-frame values map back onto the global ones exactly (n, inexact) per quantity."""

    counts: dict[str, list[int]] = field(
        default_factory=lambda: {"box_xy": [0, 0], "box_heading": [0, 0], "velocity": [0, 0]}
    )

    def add(self, name: str, exact: np.ndarray) -> None:
        self.counts[name][0] += int(exact.size)
        self.counts[name][1] += int((~exact).sum())


def _search(
    start: np.ndarray, target: np.ndarray, forward: Callable[[np.ndarray], np.ndarray], dims: int
) -> tuple[np.ndarray, np.ndarray]:
    """Return per row the offset of `start` (in ulps of its first `dims` columns) closest to the origin whose
    `forward` equals `target` exactly, and whether one was found (else `start` is kept)."""
    best = start.copy()
    found = np.all(forward(start) == target, axis=1)
    spacing = np.spacing(np.abs(start[:, :dims]))
    offsets = sorted(
        itertools.product(range(-SEARCH_ULPS, SEARCH_ULPS + 1), repeat=dims), key=lambda o: max(map(abs, o))
    )
    for offset in offsets:
        if found.all():
            break
        candidate = start.copy()
        candidate[:, :dims] = start[:, :dims] + np.array(offset) * spacing
        hit = ~found & np.all(forward(candidate) == target, axis=1)
        best[hit] = candidate[hit]
        found |= hit
    return best, found


def ego_frame_objects(frame: dict[str, Any], stats: EgoFrameStats) -> tuple[np.ndarray, np.ndarray]:
    """Return a scene frame's boxes (n, 7) and velocities (n, 3) in its ego frame, as preimages of the importer."""
    ego = frame["ego"]
    pose = EgoPose(ego["x"], ego["y"], ego["heading"])
    boxes = np.array([obj["box"] for obj in frame["objects"]], dtype=np.float64).reshape(-1, 7)
    velocities = np.array([obj["velocity"] for obj in frame["objects"]], dtype=np.float64).reshape(-1, 2)
    is_agent = np.array([obj["category"] in AGENT_CATEGORIES for obj in frame["objects"]], dtype=bool)
    rear_x, rear_y = rear_axle_round_trip(pose.x, pose.y, pose.heading)
    cos, sin = np.cos(pose.heading), np.sin(pose.heading)
    dx, dy = boxes[:, 0] - rear_x, boxes[:, 1] - rear_y
    local = boxes.copy()
    local[:, 0], local[:, 1] = dx * cos + dy * sin, -dx * sin + dy * cos
    local[:, 6] = boxes[:, 6] - pose.heading

    def forward_xy(candidate: np.ndarray) -> np.ndarray:
        return boxes_to_global(np.column_stack([candidate, local[:, 2:]]), pose)[:, :2]

    xy, exact_xy = _search(local[:, :2], boxes[:, :2], forward_xy, 2)
    local[:, :2] = xy

    def forward_heading(candidate: np.ndarray) -> np.ndarray:
        return normalize_angle(normalize_angle(candidate[:, 0] + pose.heading))[:, None]

    heading, exact_heading = _search(local[:, 6:7], boxes[:, 6:7], forward_heading, 1)
    local[:, 6] = heading[:, 0]
    vx, vy = velocities[:, 0], velocities[:, 1]
    start = np.column_stack([vx * cos + vy * sin, -vx * sin + vy * cos])
    local_velocities, exact_velocity = _search(start, velocities, lambda v: velocities_to_global(v, pose), 2)
    stats.add("box_xy", exact_xy)
    stats.add("box_heading", exact_heading)
    stats.add("velocity", exact_velocity[is_agent])
    return local, np.column_stack([local_velocities, np.zeros(len(boxes))])


# --- synthetic scene pickles -------------------------------------------------------------------------------


def _frame(frame: dict[str, Any], stats: EgoFrameStats) -> dict[str, Any]:
    """Return a scene frame as `Scene.save_to_disk` writes a frame."""
    boxes, velocities = ego_frame_objects(frame, stats)
    ego = frame["ego"]
    return {
        "token": frame["token"],
        "timestamp": frame["timestamp_us"],
        "roadblock_ids": list(frame["route_roadblocks"]),
        "traffic_lights": [(int(connector), is_red) for connector, is_red in frame["traffic_lights"]],
        "annotations": {
            "boxes": boxes,
            "names": [obj["category"] for obj in frame["objects"]],
            "velocity_3d": velocities,
            "instance_tokens": [f"{index:016x}" for index in range(len(boxes))],
            "track_tokens": [obj["track"] for obj in frame["objects"]],
        },
        "ego_status": {
            "ego_pose": np.array([ego["x"], ego["y"], ego["heading"]], dtype=np.float64),
            "ego_velocity": np.array([ego["vx"], ego["vy"]], dtype=np.float32),
            "ego_acceleration": np.array([ego["ax"], ego["ay"]], dtype=np.float32),
            "driving_command": np.array(frame["driving_command"]),
            "in_global_frame": True,
        },
        "lidar_path": None,
        "camera_dict": {
            name: {}
            for name in ("cam_f0", "cam_l0", "cam_l1", "cam_l2", "cam_r0", "cam_r1", "cam_r2", "cam_b0")
        },
    }


def detections(frame: dict[str, Any]) -> Any:
    """Return a scene frame's objects as nuPlan's `DetectionsTracks` (sorted by type, as `TrackedObjects`)."""
    objects = []
    for obj in frame["objects"]:
        x, y, _z, length, width, height, heading = obj["box"]
        kind = TrackedObjectType(CATEGORIES.index(obj["category"]))
        state: dict[str, Any] = {
            "_metadata": SceneObjectMetadata(
                timestamp_us=frame["timestamp_us"],
                token=f"{obj['track']}-{frame['timestamp_us']}",
                track_id=None,
                track_token=obj["track"],
                category_name=obj["category"],
            ),
            "instance_token": None,
            "_tracked_object_type": kind,
            "_box": OrientedBox(
                _center=StateSE2(x=x, y=y, heading=heading), _length=length, _width=width, _height=height
            ),
        }
        if obj["category"] in AGENT_CATEGORIES:
            vx, vy = obj["velocity"]
            objects.append(
                Agent(
                    _initial_time_stamp=TimePoint(time_us=frame["timestamp_us"]),
                    _predictions=[],
                    _past_trajectory=None,
                    **state,
                    _velocity=StateVector2D(_x=vx, _y=vy, _array=np.array([vx, vy])),
                    _angular_velocity=None,
                )
            )
        else:
            objects.append(StaticObject(**state))
    objects.sort(key=lambda item: item._tracked_object_type.value)
    return DetectionsTracks(tracked_objects=TrackedObjects(tracked_objects=objects))


def light_statuses(frame: dict[str, Any]) -> Any:
    """Return a scene frame's lights as nuPlan's `TrafficLightStatuses`."""
    return TrafficLightStatuses(
        traffic_lights=[
            TrafficLightStatusData(
                status=TrafficLightStatusType.RED if is_red else TrafficLightStatusType.GREEN,
                lane_connector_id=int(connector),
                timestamp=frame["timestamp_us"],
            )
            for connector, is_red in frame["traffic_lights"]
        ]
    )


def synthetic_pickle(
    scenes: list[dict[str, Any]], original: str, stats: EgoFrameStats, future_frames: int = 10
) -> dict[str, Any]:
    """Return the pickle content of one synthetic scene, or of a roll-out pair [prev2, now2] as 5 frames.

    The frames are the first scene's history and current frame (and the second's current frame); the future
    after the last frame, `future_frames` of them, becomes the extended tracks and lights."""
    first, last = scenes[0], scenes[-1]
    frames = first["frames"][:4] + [scene["frames"][3] for scene in scenes[1:]]
    future = last["frames"][4 : 4 + future_frames]
    return {
        "scene_metadata": {
            "log_name": first["log_name"],
            "scene_token": first["token"],
            "map_name": first["map_name"],
            "initial_token": first["token"],
            "num_history_frames": 4,
            "num_future_frames": 0,
            "corresponding_original_scene": None,
            "corresponding_original_initial_token": original,
        },
        "frames": [_frame(frame, stats) for frame in frames],
        "extended_traffic_light_data": [light_statuses(frame) for frame in future],
        "extended_detections_tracks": [detections(frame) for frame in future],
    }


# --- logged frames -----------------------------------------------------------------------------------------


def log_frame(frame: dict[str, Any], log_name: str, map_name: str, stats: EgoFrameStats) -> dict[str, Any]:
    """Return a scene frame as an OpenScene log frame (the rotation a quaternion of the exact heading)."""
    boxes, velocities = ego_frame_objects(frame, stats)
    ego = frame["ego"]
    return {
        "token": frame["token"],
        "timestamp": frame["timestamp_us"],
        "log_name": log_name,
        "scene_token": "0" * 16,
        "map_location": map_name,
        "roadblock_ids": list(frame["route_roadblocks"]),
        "traffic_lights": [(int(connector), is_red) for connector, is_red in frame["traffic_lights"]],
        "ego2global_translation": np.array([ego["x"], ego["y"], 0.0]),
        "ego2global_rotation": np.array(exact_yaw_quaternion(ego["heading"])),
        "ego_dynamic_state": [ego["vx"], ego["vy"], ego["ax"], ego["ay"]],
        "driving_command": np.array(frame["driving_command"]),
        "anns": {
            "gt_boxes": boxes,
            "gt_names": np.array([obj["category"] for obj in frame["objects"]]),
            "gt_velocity_3d": velocities,
            "instance_tokens": [f"{index:016x}" for index in range(len(boxes))],
            "track_tokens": [obj["track"] for obj in frame["objects"]],
        },
        "cams": {},
        "lidar_path": "",
    }


def stage_one_log(
    original: dict[str, Any], previous: dict[str, Any], stats: EgoFrameStats
) -> list[dict[str, Any]]:
    """Return one OpenScene log holding both windows: `previous`'s first frame, then `original`'s 14."""
    assert [f["token"] for f in previous["frames"][1:]] == [f["token"] for f in original["frames"][:-1]]
    frames = previous["frames"][:1] + original["frames"]
    return [log_frame(frame, original["log_name"], original["map_name"], stats) for frame in frames]
