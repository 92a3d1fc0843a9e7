"""NAVSIM synthetic scene pickles to scene files, read as NAVSIM's `NavSimScenario` reads them.

A pickle (`Scene.save_to_disk`, epdms-two-stage.md 1.1) holds `scene_metadata`, `frames` (4 history frames:
annotations in the ego frame, `ego_status.ego_pose` in the global frame) and the future that has no frames:
`extended_detections_tracks` (nuPlan `DetectionsTracks`, global boxes and velocities) and
`extended_traffic_light_data` (`TrafficLightStatuses`). The private-test form of a roll-out has 5 frames and
makes two scenes, frames[:-1] (prev2) and frames[1:] (now2); a pickle here makes one scene per frame from
the 4th on, each with the 3 frames before it as history.

As NAVSIM: frame annotations go to the global frame with the frame's own ego (`frames.boxes_to_global`);
the k-th frame after the last pickled one is extended entry k - 1, its time the last frame's + k x 0.5 s,
its ego the last frame's (never read for a 17-character token); lights are RED or not. The scene format keeps 10 future frames; v2.2 observes 8 (`versions.py`, `observation_frames`), so a
pickle with 8 or 9 future frames holds its last one to the 10th, with a warning (`frames.padded_future`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scorer.human import is_synthetic
from scorer.openscene.excerpt import build_excerpt, excerpt_to_json
from scorer.openscene.frames import (
    CURRENT_INDEX,
    FRAME_INTERVAL_S,
    OBSERVED_FUTURE_FRAMES,
    EgoPose,
    driving_command,
    global_objects,
    held_frame,
    padded_future,
    vehicle_centres,
)
from scorer.openscene.gpkg import MapTables, map_location
from scorer.openscene.scene_pickle import EnumValue, Record
from scorer.scene import AGENT_CATEGORIES, CATEGORIES, SCENE_FORMAT, SCENE_VERSION

RED = 2  # nuPlan TrafficLightStatusType.RED
# nuPlan TrackedObjectType values 0-6 are the categories in the scene format's order (EGO = 7 is no object).
OBJECT_TYPES = dict(enumerate(CATEGORIES))
# NAVSIM's Annotations dataclass, as `asdict` writes it into a frame.
PICKLE_ANNOTATION_KEYS = ("boxes", "names", "velocity_3d", "instance_tokens", "track_tokens")


class SyntheticSceneError(ValueError):
    """A synthetic scene pickle that cannot become a scene; the message names the file, token and field."""


@dataclass(frozen=True)
class SyntheticScene:
    """One scene of a pickle, ready to write (None where not asked for), and what the conversion had to say."""

    token: str
    scene: dict[str, Any] | None
    warnings: tuple[str, ...]


class _Where:
    """Names the file and the field of every error."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, where: str, message: str) -> SyntheticSceneError:
        return SyntheticSceneError(f"{self.path}: {where}: {message}")

    def get(self, obj: Any, key: str, where: str) -> Any:
        if not isinstance(obj, Mapping):
            raise self.fail(where, f"expected a dict, got {type(obj).__name__}")
        if key not in obj:
            raise self.fail(f"{where}.{key}" if where else key, "missing")
        return obj[key]

    def record(self, obj: Any, kind: str, where: str) -> Mapping[str, Any]:
        if not isinstance(obj, Record) or obj.kind != kind:
            raise self.fail(
                where, f"expected a nuPlan {kind}, got {getattr(obj, 'kind', type(obj).__name__)}"
            )
        return obj.state

    def numbers(self, value: Any, where: str, shape: tuple[int, ...]) -> np.ndarray:
        try:
            array = np.asarray(value, dtype=np.float64).reshape(shape)
        except (TypeError, ValueError):
            raise self.fail(where, f"expected numbers of shape {shape}") from None
        if not np.all(np.isfinite(array)):
            raise self.fail(where, "non-finite value")
        return array

    def number(self, value: Any, where: str) -> float:
        return float(self.numbers(value, where, ()))


def synthetic_scenes(
    path: Path,
    content: Any,
    tables: Callable[[str], MapTables],
    build: Callable[[str], bool] = lambda token: True,
) -> list[SyntheticScene]:
    """Return the scenes of a loaded synthetic scene pickle, every one checked, those `build` wants (by token)
    made, with their map excerpts (`tables(location)` gives a map's tables)."""
    at = _Where(path)
    if isinstance(content, list):
        raise at.fail(
            "(top level)",
            "a list of frames is the private-test agent input (no annotations, no future objects); "
            "a scene needs a Scene.save_to_disk pickle (a dict with scene_metadata, frames and the extended "
            "tracks)",
        )
    metadata = at.get(content, "scene_metadata", "")
    raw_frames = at.get(content, "frames", "")
    if not isinstance(raw_frames, list) or len(raw_frames) <= CURRENT_INDEX:
        raise at.fail("frames", f"expected a list of at least {CURRENT_INDEX + 1} frames")
    frames = [_frame(at, raw, f"frames[{index}]") for index, raw in enumerate(raw_frames)]
    detections = content.get("extended_detections_tracks") if isinstance(content, Mapping) else None
    lights = content.get("extended_traffic_light_data") if isinstance(content, Mapping) else None
    extended = _extended_frames(at, frames[-1], detections or [], lights or [])
    log_name = at.get(metadata, "log_name", "scene_metadata")
    map_name = at.get(metadata, "map_name", "scene_metadata")
    if not isinstance(log_name, str) or not log_name or not isinstance(map_name, str):
        raise at.fail("scene_metadata", "log_name and map_name must be text")
    try:
        location = map_location(map_name)
    except ValueError as error:
        raise at.fail("scene_metadata.map_name", str(error)) from None
    scenes = []
    for current in range(CURRENT_INDEX, len(frames)):
        token = frames[current]["token"]
        where = f"frames[{current}] (token {token})"
        if not is_synthetic(token):
            raise at.fail(where, "a synthetic scene's token has 17 characters (NAVSIM's test)")
        future = frames[current + 1 :] + extended
        if len(future) < OBSERVED_FUTURE_FRAMES:
            raise at.fail(
                where,
                f"{len(future)} future frame(s) (frames after it and extended_detections_tracks); "
                f"the observation needs {OBSERVED_FUTURE_FRAMES}",
            )
        future, warnings = padded_future(future)
        if not build(token):
            scenes.append(SyntheticScene(token, None, warnings))
            continue
        ego = frames[current]["ego"]
        pose = EgoPose(ego["x"], ego["y"], ego["heading"])
        excerpt = build_excerpt(
            tables(location),
            pose,
            frames[current]["route_roadblocks"],
            vehicle_centres(frames[current]["objects"]),
        )
        scene = {
            "format": SCENE_FORMAT,
            "version": SCENE_VERSION,
            "token": token,
            "log_name": log_name,
            "map_name": location,
            "frame_interval_s": FRAME_INTERVAL_S,
            "current_index": CURRENT_INDEX,
            "frames": frames[current - CURRENT_INDEX : current + 1] + future,
            "map": excerpt_to_json(excerpt.map),
        }
        scenes.append(SyntheticScene(token, scene, (*excerpt.warnings, *warnings)))
    return scenes


def _frame(at: _Where, raw: Any, where: str) -> dict[str, Any]:
    """Return the scene-file frame of a pickled NAVSIM frame."""
    token = at.get(raw, "token", where)
    if not isinstance(token, str) or not token:
        raise at.fail(f"{where}.token", f"expected a token, got {token!r}")
    where = f"{where} (token {token})"
    timestamp = at.get(raw, "timestamp", where)
    if isinstance(timestamp, bool) or not isinstance(timestamp, (int, np.integer)):
        raise at.fail(f"{where}.timestamp", f"expected an integer (us), got {timestamp!r}")
    status = at.get(raw, "ego_status", where)
    ego_where = f"{where}.ego_status"

    def ego_values(key: str, size: int) -> np.ndarray:
        return at.numbers(at.get(status, key, ego_where), f"{ego_where}.{key}", (size,))

    x, y, heading = ego_values("ego_pose", 3)
    dynamics = [*ego_values("ego_velocity", 2), *ego_values("ego_acceleration", 2)]
    command = driving_command({"driving_command": at.get(status, "driving_command", ego_where)})
    if command is None:
        raise at.fail(
            f"{where}.ego_status.driving_command", "expected a one-hot [left, straight, right, unknown]"
        )
    pose = EgoPose(float(x), float(y), float(heading))
    return {
        "token": token,
        "timestamp_us": int(timestamp),
        "ego": {
            "x": pose.x,
            "y": pose.y,
            "heading": pose.heading,
            **dict(zip(("vx", "vy", "ax", "ay"), map(float, dynamics), strict=True)),
        },
        "driving_command": command,
        "objects": _annotated_objects(at, at.get(raw, "annotations", where), pose, f"{where}.annotations"),
        "traffic_lights": _frame_lights(at, at.get(raw, "traffic_lights", where), f"{where}.traffic_lights"),
        "route_roadblocks": _ids(at, at.get(raw, "roadblock_ids", where), f"{where}.roadblock_ids"),
    }


def _annotated_objects(at: _Where, raw: Any, pose: EgoPose, where: str) -> list[dict[str, Any]]:
    columns = {key: at.get(raw, key, where) for key in PICKLE_ANNOTATION_KEYS}
    lengths = {key: len(value) for key, value in columns.items() if hasattr(value, "__len__")}
    if len(lengths) != len(columns) or len(set(lengths.values())) != 1:
        raise at.fail(where, f"annotation lists differ in length {lengths}")
    count = lengths["boxes"]
    local_boxes = at.numbers(columns["boxes"], f"{where}.boxes", (count, 7))
    local_velocities = at.numbers(columns["velocity_3d"], f"{where}.velocity_3d", (count, 3))
    categories = [str(name) for name in columns["names"]]
    unknown = sorted(set(categories) - set(CATEGORIES))
    if unknown:
        raise at.fail(f"{where}.names", f"unknown class(es) {unknown}; expected one of {CATEGORIES}")
    return global_objects(columns["track_tokens"], categories, local_boxes, local_velocities, pose)


def _frame_lights(at: _Where, raw: Any, where: str) -> list[list[Any]]:
    if not isinstance(raw, Sequence):
        raise at.fail(where, "expected a list of (lane_connector_id, is_red)")
    lights = []
    for index, light in enumerate(raw):
        if not (isinstance(light, Sequence) and len(light) == 2):
            raise at.fail(f"{where}[{index}]", f"expected (lane_connector_id, is_red), got {light!r}")
        lights.append([_id(at, light[0], f"{where}[{index}]"), bool(light[1])])
    return lights


def _id(at: _Where, value: Any, where: str) -> str:
    text = str(int(value)) if isinstance(value, (int, np.integer)) and not isinstance(value, bool) else value
    if not isinstance(text, str) or not text.isdigit():
        raise at.fail(where, f"map id {value!r} is not a decimal integer")
    return text


def _ids(at: _Where, raw: Any, where: str) -> list[str]:
    if not isinstance(raw, Sequence) or isinstance(raw, str):
        raise at.fail(where, "expected a list of map ids")
    return [_id(at, value, f"{where}[{index}]") for index, value in enumerate(raw)]


def _extended_frames(
    at: _Where, last: dict[str, Any], detections: Any, statuses: Any
) -> list[dict[str, Any]]:
    """Return the frames of the extended future, in NavSimScenario's terms."""
    if not isinstance(detections, list) or not isinstance(statuses, list):
        raise at.fail("extended_detections_tracks", "extended tracks and lights must be lists")
    frames = []
    for index, tracks in enumerate(detections):
        where = f"extended_detections_tracks[{index}]"
        frame = held_frame(last, index + 1)
        frame["objects"] = _tracked_objects(at, tracks, where)
        frame["traffic_lights"] = (
            _status_lights(at, statuses[index], f"extended_traffic_light_data[{index}]")
            if index < len(statuses)
            else []  # NavSimScenario yields no lights where the extended data end
        )
        frames.append(frame)
    return frames


def _tracked_objects(at: _Where, raw: Any, where: str) -> list[dict[str, Any]]:
    detections = at.record(raw, "DetectionsTracks", where)
    tracked = at.record(
        at.get(detections, "tracked_objects", where), "TrackedObjects", f"{where}.tracked_objects"
    )
    items = at.get(tracked, "tracked_objects", f"{where}.tracked_objects")
    if not isinstance(items, list):
        raise at.fail(f"{where}.tracked_objects", "expected a list")
    objects = []
    for index, item in enumerate(items):
        at_item = f"{where}.tracked_objects[{index}]"
        if not isinstance(item, Record) or item.kind not in ("Agent", "StaticObject", "SceneObject"):
            raise at.fail(
                at_item, f"expected a nuPlan Agent or StaticObject, got {getattr(item, 'kind', item)!r}"
            )
        state = item.state
        kind = at.get(state, "_tracked_object_type", at_item)
        if (
            not isinstance(kind, EnumValue)
            or kind.kind != "TrackedObjectType"
            or kind.value not in OBJECT_TYPES
        ):
            raise at.fail(f"{at_item}._tracked_object_type", f"expected an object type, got {kind!r}")
        category = OBJECT_TYPES[kind.value]
        metadata = at.record(
            at.get(state, "_metadata", at_item), "SceneObjectMetadata", f"{at_item}._metadata"
        )
        track = at.get(metadata, "track_token", f"{at_item}._metadata")
        if not isinstance(track, str) or not track:
            raise at.fail(f"{at_item}._metadata.track_token", f"expected a track token, got {track!r}")
        box = at.record(at.get(state, "_box", at_item), "OrientedBox", f"{at_item}._box")
        center = at.record(at.get(box, "_center", f"{at_item}._box"), "StateSE2", f"{at_item}._box._center")
        x, y, heading = (
            at.number(at.get(center, key, f"{at_item}._box._center"), f"{at_item}._box._center.{key}")
            for key in ("x", "y", "heading")
        )
        length, width, height = (
            at.number(at.get(box, key, f"{at_item}._box"), f"{at_item}._box.{key}")
            for key in ("_length", "_width", "_height")
        )
        velocity = [0.0, 0.0]
        if category in AGENT_CATEGORIES:
            vector = at.record(at.get(state, "_velocity", at_item), "StateVector2D", f"{at_item}._velocity")
            velocity = [
                at.number(at.get(vector, key, f"{at_item}._velocity"), f"{at_item}._velocity")
                for key in ("_x", "_y")
            ]
        # nuPlan boxes are 2-D: z (unused) is 0.
        box_values = [x, y, 0.0, length, width, height, heading]
        objects.append({"track": track, "category": category, "box": box_values, "velocity": velocity})
    return objects


def _status_lights(at: _Where, raw: Any, where: str) -> list[list[Any]]:
    statuses = at.record(raw, "TrafficLightStatuses", where)
    items = at.get(statuses, "traffic_lights", where)
    if not isinstance(items, list):
        raise at.fail(f"{where}.traffic_lights", "expected a list")
    lights = []
    for index, item in enumerate(items):
        at_item = f"{where}.traffic_lights[{index}]"
        data = at.record(item, "TrafficLightStatusData", at_item)
        status = at.get(data, "status", at_item)
        if not isinstance(status, EnumValue) or status.kind != "TrafficLightStatusType":
            raise at.fail(f"{at_item}.status", f"expected a traffic light status, got {status!r}")
        lights.append(
            [
                _id(at, at.get(data, "lane_connector_id", at_item), f"{at_item}.lane_connector_id"),
                status.value == RED,
            ]
        )
    return lights
