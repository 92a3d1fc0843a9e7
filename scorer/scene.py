"""The `navsim-lb/scene` v1 file: typed in-memory model, reader and validator (scene-format.md).

Every broken rule raises `SceneFormatError` naming the file and the field; nothing is guessed.
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
import hashlib
import json
import math
import re
import stat
import time
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from itertools import chain
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import shapely

from scorer.collector import collector_paused
from scorer.geometry import FloatArray
from scorer.json_reading import read_json

SCENE_FORMAT = "navsim-lb/scene"
SCENE_VERSION = 1
AGENT_CATEGORIES = ("vehicle", "pedestrian", "bicycle")
STATIC_CATEGORIES = ("traffic_cone", "barrier", "czone_sign", "generic_object")
CATEGORIES = AGENT_CATEGORIES + STATIC_CATEGORIES
_CATEGORY_SET = frozenset(CATEGORIES)
FUTURE_FRAMES = 10  # the engine observes current + 10 frames (5 s at 2 Hz)
AREA_LAYERS = ("intersections", "carpark_areas", "drivable_areas", "crosswalks", "walkways")
# A map id of digits (`_Reader.check_id`) with a leading zero, in ids joined by spaces (compiled on first use).
_LEADING_ZERO = r"(?:^| )0[^ ]"


def _canonical_ids(ids: list[str]) -> bool:
    """Return whether every map id is a canonical decimal integer (`_Reader.check_id`), in two calls."""
    return all(map(str.isdigit, ids)) and re.search(_LEADING_ZERO, " ".join(ids)) is None


class SceneFormatError(ValueError):
    """A scene file breaks a rule of the format; the message names the file and the field."""


class EgoStatus(NamedTuple):
    """Rear-axle pose (global frame) and rear-axle dynamics (ego frame; float32-rounded as NAVSIM holds them)."""

    x: float
    y: float
    heading: float
    vx: float
    vy: float
    ax: float
    ay: float


class Frame(NamedTuple):
    """One 2 Hz frame. Objects are column arrays (one row per object, annotation order)."""

    token: str
    timestamp_us: int
    ego: EgoStatus
    driving_command: tuple[int, int, int, int]
    tracks: tuple[str, ...]
    categories: tuple[str, ...]
    boxes: FloatArray  # (n, 7): x, y, z, length, width, height, heading
    velocities: FloatArray  # (n, 2) global frame
    traffic_lights: tuple[tuple[str, bool], ...]
    route_roadblocks: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class Lane:
    """A lane or a lane connector (`roadblock` then names a roadblock connector)."""

    id: str
    polygon: shapely.Polygon
    roadblock: str
    baseline: FloatArray  # (n, 2)
    speed_limit_mps: float | None
    incoming: tuple[str, ...]
    outgoing: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class Roadblock:
    """A roadblock or a roadblock connector."""

    id: str
    polygon: shapely.Polygon
    incoming: tuple[str, ...]
    outgoing: tuple[str, ...]
    lanes: tuple[str, ...]


class Area(NamedTuple):
    """A polygon-only map object (intersection, car park, generic drivable area, crosswalk, walkway)."""

    id: str
    polygon: shapely.Polygon


class MapExcerpt(NamedTuple):
    """Map layers in file order (the order decides the devkit's tie-breaks)."""

    lanes: tuple[Lane, ...]
    lane_connectors: tuple[Lane, ...]
    roadblocks: tuple[Roadblock, ...]
    roadblock_connectors: tuple[Roadblock, ...]
    intersections: tuple[Area, ...] = ()
    carpark_areas: tuple[Area, ...] = ()
    drivable_areas: tuple[Area, ...] = ()
    crosswalks: tuple[Area, ...] = ()
    walkways: tuple[Area, ...] = ()


class Scene(NamedTuple):
    """A hidden-log scene: frames in time order, the current frame index and the map excerpt."""

    token: str
    log_name: str
    map_name: str
    frame_interval_s: float
    current_index: int
    frames: tuple[Frame, ...]
    map: MapExcerpt
    content_hash: str = ""

    @property
    def current_frame(self) -> Frame:
        """Return the current (initial) frame."""
        return self.frames[self.current_index]

    @property
    def future_frames(self) -> tuple[Frame, ...]:
        """Return the current frame and the 10 frames after it: what the engine observes."""
        return self.frames[self.current_index : self.current_index + FUTURE_FRAMES + 1]


class _Reader:
    """Typed field access that names the file and the JSON path of every error."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, where: str, message: str) -> SceneFormatError:
        return SceneFormatError(f"{self.source}: {where}: {message}")

    def get(self, obj: dict[str, Any], key: str, where: str) -> Any:
        if not isinstance(obj, dict):
            raise self.fail(where, "expected an object")
        if key not in obj:
            raise self.fail(f"{where}.{key}" if where else key, "missing field")
        return obj[key]

    def string(self, obj: dict[str, Any], key: str, where: str) -> str:
        value = self.get(obj, key, where)
        if not isinstance(value, str) or not value:
            raise self.fail(self.path(where, key), f"expected a non-empty string, got {value!r}")
        return value

    def integer(self, value: Any, where: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(where, f"expected an integer, got {value!r}")
        return value

    def number(self, value: Any, where: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(where, f"expected a finite number, got {value!r}")
        return float(value)

    def array(self, value: Any, where: str, shape: tuple[int | None, ...]) -> FloatArray:
        try:
            result = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(where, f"expected numbers of shape {_shape_text(shape)}") from None
        if result.ndim != len(shape) or any(
            n is not None and n != m for n, m in zip(shape, result.shape, strict=True)
        ):
            raise self.fail(where, f"expected shape {_shape_text(shape)}, got {result.shape}")
        if not np.isfinite(result).all():
            raise self.fail(where, "non-finite value")
        return result

    def id_list(self, obj: dict[str, Any], key: str, where: str) -> tuple[str, ...]:
        value = self.get(obj, key, where)
        if not isinstance(value, list) or not (
            set(map(type, value)) <= {str} or all(isinstance(item, str) for item in value)
        ):
            raise self.fail(self.path(where, key), "expected a list of id strings")
        # Most lists pass: checked in two calls; otherwise item by item, to name the first bad one.
        if not _canonical_ids(value):
            for item in value:
                self.check_id(item, self.path(where, key))
        return tuple(value)

    def check_id(self, value: str, where: str) -> None:
        # nuPlan casts map ids with int(); accept canonical decimal integers only.
        if not value.isdigit() or (len(value) > 1 and value[0] == "0"):
            raise self.fail(where, f"map id {value!r} is not a decimal integer")

    @staticmethod
    def path(where: str, key: str) -> str:
        return f"{where}.{key}" if where else key


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("n" if n is None else str(n) for n in shape) + ")"


def _read_ego(reader: _Reader, raw: Any, where: str) -> EgoStatus:
    values = {key: reader.number(reader.get(raw, key, where), f"{where}.{key}") for key in EgoStatus._fields}
    if not -math.pi <= values["heading"] <= math.pi:
        raise reader.fail(f"{where}.heading", f"angle {values['heading']} outside [-pi, pi]")
    # NAVSIM holds the ego dynamics as float32 (Scene._build_ego_status); the last bits decide NC/TTC.
    for key in ("vx", "vy", "ax", "ay"):
        values[key] = float(np.float32(values[key]))
    return EgoStatus(**values)


def _valid_object_columns(raw_objects: list[Any]) -> tuple[FloatArray, FloatArray] | None:
    """Return a frame's boxes (n, 7) and velocities (n, 2) when every object's are valid, each converted as
    `_Reader.array` converts it, else None: then `_read_frame` reads them object by object, to name the first
    invalid field. Most of a scene's numbers are there, and one call per frame costs less than one per object.
    """
    count = len(raw_objects)
    try:
        boxes = np.asarray([item["box"] for item in raw_objects], dtype=np.float64)
        velocities = np.asarray([item["velocity"] for item in raw_objects], dtype=np.float64)
    except (TypeError, KeyError, ValueError, OverflowError):
        return None
    if boxes.shape != (count, 7) or velocities.shape != (count, 2):
        return None
    if not (np.isfinite(boxes).all() and np.isfinite(velocities).all() and (boxes[:, 3:5] > 0).all()):
        return None
    return boxes, velocities


def _valid_object_names(raw_objects: list[Any]) -> tuple[list[str], list[str]] | None:
    """Return a frame's tracks and categories when every object's are valid (as `_read_frame` checks them one
    by one), else None: two passes over the frame (reading object by object was a tenth of a scene's parsing)."""
    try:
        tracks = [item["track"] for item in raw_objects]
        categories = [item["category"] for item in raw_objects]
        names_valid = set(map(type, tracks)) <= {str} and all(tracks) and set(categories) <= _CATEGORY_SET
    except (TypeError, KeyError):  # not an object, a field missing, an unhashable category
        return None
    return (tracks, categories) if names_valid else None


def _read_objects(
    reader: _Reader, raw_objects: list[Any], where: str, arrays: bool
) -> tuple[list[str], list[str], list[FloatArray], list[FloatArray]]:
    """Return a frame's tracks, categories and, where `arrays`, boxes and velocities, object by object: the
    first invalid field is named."""
    tracks, categories, boxes, velocities = [], [], [], []
    for index, raw_object in enumerate(raw_objects):
        at = f"{where}.objects[{index}]"
        tracks.append(reader.string(raw_object, "track", at))
        category = reader.get(raw_object, "category", at)
        if category not in CATEGORIES:
            raise reader.fail(
                f"{at}.category", f"unknown category {category!r}; expected one of {CATEGORIES}"
            )
        categories.append(category)
        if not arrays:  # every box and velocity is valid: read in one call (`_valid_object_columns`)
            continue
        box = reader.array(reader.get(raw_object, "box", at), f"{at}.box", (7,))
        if box[3] <= 0 or box[4] <= 0:
            raise reader.fail(f"{at}.box", "length and width must be positive")
        boxes.append(box)
        velocities.append(reader.array(reader.get(raw_object, "velocity", at), f"{at}.velocity", (2,)))
    return tracks, categories, boxes, velocities


def _read_frame(reader: _Reader, raw: Any, where: str) -> Frame:
    token = reader.string(raw, "token", where)
    timestamp_us = reader.integer(reader.get(raw, "timestamp_us", where), f"{where}.timestamp_us")
    ego = _read_ego(reader, reader.get(raw, "ego", where), f"{where}.ego")
    command = reader.get(raw, "driving_command", where)
    if (
        not isinstance(command, list)
        or len(command) != 4
        or any(isinstance(c, bool) or c not in (0, 1) for c in command)
    ):
        raise reader.fail(f"{where}.driving_command", f"expected 4 ints 0/1, got {command!r}")
    raw_objects = reader.get(raw, "objects", where)
    if not isinstance(raw_objects, list):
        raise reader.fail(f"{where}.objects", "expected a list")
    columns = _valid_object_columns(raw_objects)
    names = None if columns is None else _valid_object_names(raw_objects)
    if names is None:
        tracks, categories, boxes, velocities = _read_objects(reader, raw_objects, where, columns is None)
    else:  # every object is valid: nothing to read one by one
        (tracks, categories), boxes, velocities = names, [], []
    if len(set(tracks)) != len(tracks):
        raise reader.fail(f"{where}.objects", "a track appears twice in one frame")
    raw_lights = reader.get(raw, "traffic_lights", where)
    if not isinstance(raw_lights, list):
        raise reader.fail(f"{where}.traffic_lights", "expected a list of [lane_connector_id, is_red] pairs")
    lights = []
    for index, light in enumerate(raw_lights):
        at = f"{where}.traffic_lights[{index}]"
        if not (
            isinstance(light, list)
            and len(light) == 2
            and isinstance(light[0], str)
            and isinstance(light[1], bool)
        ):
            raise reader.fail(at, f"expected [lane_connector_id, is_red], got {light!r}")
        reader.check_id(light[0], at)
        lights.append((light[0], light[1]))
    return Frame(
        token=token,
        timestamp_us=timestamp_us,
        ego=ego,
        driving_command=tuple(command),
        tracks=tuple(tracks),
        categories=tuple(categories),
        boxes=np.array(boxes, dtype=np.float64).reshape(len(boxes), 7) if columns is None else columns[0],
        velocities=(
            np.array(velocities, dtype=np.float64).reshape(len(velocities), 2)
            if columns is None
            else columns[1]
        ),
        traffic_lights=tuple(lights),
        route_roadblocks=reader.id_list(raw, "route_roadblocks", where),
    )


def _read_ring(reader: _Reader, raw: Any, where: str) -> FloatArray:
    ring = reader.array(reader.get(raw, "polygon", where), f"{where}.polygon", (None, 2))
    if len(ring) < 3:
        raise reader.fail(f"{where}.polygon", f"a polygon needs at least 3 vertices, got {len(ring)}")
    return ring


def _read_baseline(reader: _Reader, raw: Any, where: str) -> FloatArray:
    baseline = reader.array(reader.get(raw, "baseline", where), f"{where}.baseline", (None, 2))
    if len(baseline) < 2:
        raise reader.fail(f"{where}.baseline", "a baseline needs at least 2 vertices")
    return baseline


PointLists = tuple[FloatArray, list[int]]  # a layer's point lists end to end (N, 2), and each list's length


def _valid_point_lists(raw_layer: list[Any], key: str, minimum: int) -> PointLists | None:
    """Return the point lists under `key` of a layer's objects (rings or baselines) when every one is valid
    with at least `minimum` points, each point converted as `_Reader.array` converts it, else None: then the
    layer's are read object by object (`_read_ring`, `_read_baseline`), to name the first invalid field. One
    conversion per layer costs less than one per object (a third of a scene's map reading)."""
    try:
        lists = [raw[key] for raw in raw_layer]
        if not set(map(type, lists)) <= {list}:
            return None
        counts = [len(points) for points in lists]
        pairs = list(chain.from_iterable(lists))
        # Every point a list of two: then the flat numbers convert as the nested lists do, in half the time.
        if not (set(map(type, pairs)) <= {list} and set(map(len, pairs)) <= {2}):
            return None
        numbers = np.array(list(chain.from_iterable(pairs)), dtype=np.float64)
    except (TypeError, KeyError, ValueError, OverflowError):
        return None
    if numbers.shape != (2 * len(pairs),) or min(counts, default=minimum) < minimum:
        return None
    return (numbers.reshape(-1, 2), counts) if np.isfinite(numbers).all() else None


def _valid_id_lists(raw_layer: list[Any], keys: tuple[str, ...]) -> list[tuple[tuple[str, ...], ...]] | None:
    """Return the id lists under `keys` of each of a layer's objects when every one is valid (as
    `_Reader.id_list` checks them one by one), else None: then each is read object by object, to name the first
    invalid one. Checked in a few calls per layer (one list at a time was a tenth of a scene's parsing)."""
    try:
        lists = [tuple(raw[key] for key in keys) for raw in raw_layer]
    except (TypeError, KeyError):  # not an object, a field missing
        return None
    values = list(chain.from_iterable(lists))
    if not set(map(type, values)) <= {list}:
        return None
    ids = list(chain.from_iterable(values))
    if not (set(map(type, ids)) <= {str} and _canonical_ids(ids)):
        return None
    return [tuple(map(tuple, object_lists)) for object_lists in lists]


def _joined(point_lists: list[FloatArray]) -> PointLists:
    return np.concatenate(point_lists) if point_lists else np.empty((0, 2)), [len(p) for p in point_lists]


def _split(point_lists: PointLists) -> list[FloatArray]:
    points, counts = point_lists
    ends = np.cumsum(counts).tolist()
    return [points[end - count : end] for end, count in zip(ends, counts, strict=True)]


def _polygons(rings: PointLists) -> list[shapely.Polygon]:
    """Return a layer's polygons, the same geometries as `shapely.polygons(ring)` of each ring, built in one
    call (a call per polygon was a tenth of a scene's parsing). Used as given: each ring is closed implicitly
    and never repaired (as the reference run did)."""
    points, counts = rings
    if not counts:
        return []
    ring_of = np.repeat(np.arange(len(counts)), counts)
    return list(shapely.polygons(shapely.linearrings(points, indices=ring_of)))


def _read_lanes(reader: _Reader, raw_layer: list[Any], layer: str) -> tuple[Lane, ...]:
    lanes: list[dict[str, Any]] = []  # each lane's fields but its polygon and baseline, read with the layer's
    valid_rings = _valid_point_lists(raw_layer, "polygon", 3)
    valid_baselines = _valid_point_lists(raw_layer, "baseline", 2)
    valid_edges = _valid_id_lists(raw_layer, ("incoming", "outgoing"))
    rings, baselines = [], []  # read one by one where one of the layer's is invalid, in the fields' order
    for index, raw in enumerate(raw_layer):
        where = f"map.{layer}[{index}]"
        lane_id = reader.string(raw, "id", where)
        reader.check_id(lane_id, f"{where}.id")
        roadblock = reader.string(raw, "roadblock", where)
        reader.check_id(roadblock, f"{where}.roadblock")
        if valid_baselines is None:
            baselines.append(_read_baseline(reader, raw, where))
        speed_limit = reader.get(raw, "speed_limit_mps", where)
        if speed_limit is not None:
            speed_limit = reader.number(speed_limit, f"{where}.speed_limit_mps")
            if speed_limit <= 0:
                raise reader.fail(f"{where}.speed_limit_mps", "must be positive or null")
        if valid_rings is None:
            rings.append(_read_ring(reader, raw, where))
        incoming, outgoing = (
            (reader.id_list(raw, "incoming", where), reader.id_list(raw, "outgoing", where))
            if valid_edges is None
            else valid_edges[index]
        )
        lanes.append(
            {
                "id": lane_id,
                "roadblock": roadblock,
                "speed_limit_mps": speed_limit,
                "incoming": incoming,
                "outgoing": outgoing,
            }
        )
    polygons = _polygons(_joined(rings) if valid_rings is None else valid_rings)
    lane_baselines = baselines if valid_baselines is None else _split(valid_baselines)
    return tuple(
        Lane(polygon=polygon, baseline=baseline, **lane)
        for lane, polygon, baseline in zip(lanes, polygons, lane_baselines, strict=True)
    )


def _read_roadblocks(reader: _Reader, raw_layer: list[Any], layer: str) -> tuple[Roadblock, ...]:
    blocks: list[dict[str, Any]] = []  # as `_read_lanes`
    valid_rings = _valid_point_lists(raw_layer, "polygon", 3)
    valid_lists = _valid_id_lists(raw_layer, ("incoming", "outgoing", "lanes"))
    rings = []
    for index, raw in enumerate(raw_layer):
        where = f"map.{layer}[{index}]"
        block_id = reader.string(raw, "id", where)
        reader.check_id(block_id, f"{where}.id")
        if valid_rings is None:
            rings.append(_read_ring(reader, raw, where))
        incoming, outgoing, lanes = (
            tuple(reader.id_list(raw, key, where) for key in ("incoming", "outgoing", "lanes"))
            if valid_lists is None
            else valid_lists[index]
        )
        blocks.append({"id": block_id, "incoming": incoming, "outgoing": outgoing, "lanes": lanes})
    polygons = _polygons(_joined(rings) if valid_rings is None else valid_rings)
    return tuple(Roadblock(polygon=polygon, **block) for block, polygon in zip(blocks, polygons, strict=True))


def _read_areas(reader: _Reader, raw_layer: list[Any], layer: str) -> tuple[Area, ...]:
    valid_rings = _valid_point_lists(raw_layer, "polygon", 3)
    ids, rings = [], []
    for index, raw in enumerate(raw_layer):
        where = f"map.{layer}[{index}]"
        area_id = reader.string(raw, "id", where)
        reader.check_id(area_id, f"{where}.id")
        ids.append(area_id)
        if valid_rings is None:
            rings.append(_read_ring(reader, raw, where))
    polygons = _polygons(_joined(rings) if valid_rings is None else valid_rings)
    return tuple(Area(id=area_id, polygon=polygon) for area_id, polygon in zip(ids, polygons, strict=True))


def _read_map(reader: _Reader, raw: Any) -> MapExcerpt:
    if not isinstance(raw, dict):
        raise reader.fail("map", "expected an object of layers")
    known = {"lanes", "lane_connectors", "roadblocks", "roadblock_connectors", *AREA_LAYERS}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise reader.fail("map", f"unknown layer(s) {unknown}")

    def layer(name: str, required: bool) -> list[Any]:
        if name not in raw:
            if required:
                raise reader.fail(f"map.{name}", "missing layer")
            return []
        if not isinstance(raw[name], list):
            raise reader.fail(f"map.{name}", "expected a list")
        return raw[name]

    excerpt = MapExcerpt(
        lanes=_read_lanes(reader, layer("lanes", True), "lanes"),
        lane_connectors=_read_lanes(reader, layer("lane_connectors", True), "lane_connectors"),
        roadblocks=_read_roadblocks(reader, layer("roadblocks", True), "roadblocks"),
        roadblock_connectors=_read_roadblocks(
            reader, layer("roadblock_connectors", True), "roadblock_connectors"
        ),
        **{name: _read_areas(reader, layer(name, False), name) for name in AREA_LAYERS},
    )
    _check_map_ids(reader, excerpt)
    _check_lane_graph(reader, excerpt)
    return excerpt


def _check_map_ids(reader: _Reader, excerpt: MapExcerpt) -> None:
    for name in ("lanes", "lane_connectors", "roadblocks", "roadblock_connectors", *AREA_LAYERS):
        seen: set[str] = set()
        for index, item in enumerate(getattr(excerpt, name)):
            if item.id in seen:
                raise reader.fail(f"map.{name}[{index}].id", f"duplicate id {item.id!r}")
            seen.add(item.id)


def _check_lane_graph(reader: _Reader, excerpt: MapExcerpt) -> None:
    """Connectors define the graph; the lists on lanes and roadblocks must agree with it as sets."""
    for layer, connectors in (
        ("lane_connectors", excerpt.lane_connectors),
        ("roadblock_connectors", excerpt.roadblock_connectors),
    ):
        connector_ids = {connector.id for connector in connectors}
        for index, connector in enumerate(connectors):
            for key in ("incoming", "outgoing"):
                ids = getattr(connector, key)
                if len(ids) != 1:
                    raise reader.fail(
                        f"map.{layer}[{index}].{key}", f"a connector joins exactly one, got {list(ids)}"
                    )
                if ids[0] in connector_ids:
                    raise reader.fail(
                        f"map.{layer}[{index}].{key}", "a connector cannot join another connector"
                    )
    _check_edges(reader, "lanes", excerpt.lanes, excerpt.lane_connectors)
    _check_edges(reader, "roadblocks", excerpt.roadblocks, excerpt.roadblock_connectors)
    for layer, owners, members in (
        ("roadblocks", excerpt.roadblocks, excerpt.lanes),
        ("roadblock_connectors", excerpt.roadblock_connectors, excerpt.lane_connectors),
    ):
        member_ids = {member.id for member in members}
        members_of: dict[str, set[str]] = {}
        for member in members:
            members_of.setdefault(member.roadblock, set()).add(member.id)
        for index, owner in enumerate(owners):
            derived = members_of.get(owner.id, set())
            listed = {lane for lane in owner.lanes if lane in member_ids}
            if derived != listed:
                raise reader.fail(
                    f"map.{layer}[{index}].lanes",
                    f"lists {sorted(listed)} but the excerpt's members of {owner.id} are {sorted(derived)}",
                )


def _check_edges(reader: _Reader, layer: str, nodes: tuple[Any, ...], connectors: tuple[Any, ...]) -> None:
    connector_ids = {connector.id for connector in connectors}
    # The connectors at each node's end, found in one pass (one per node and end was quadratic in the excerpt).
    joined: dict[tuple[str, str], set[str]] = {}
    for connector in connectors:
        for end in ("incoming", "outgoing"):
            joined.setdefault((end, getattr(connector, end)[0]), set()).add(connector.id)
    for index, node in enumerate(nodes):
        for key, end in (("outgoing", "incoming"), ("incoming", "outgoing")):
            derived = joined.get((end, node.id), set())
            listed = {item for item in getattr(node, key) if item in connector_ids}
            if derived != listed:
                raise reader.fail(
                    f"map.{layer}[{index}].{key}",
                    f"lists {sorted(listed)} but the connectors give {sorted(derived)}",
                )


def parse_scene(raw: Any, source: str, content_hash: str = "") -> Scene:
    """Return the validated scene of an already decoded JSON document."""
    reader = _Reader(source)
    if not isinstance(raw, dict):
        raise reader.fail("(top level)", "expected a JSON object")
    if raw.get("format") != SCENE_FORMAT:
        raise reader.fail("format", f"expected {SCENE_FORMAT!r}, got {raw.get('format')!r}")
    if raw.get("version") != SCENE_VERSION:
        raise reader.fail("version", f"unsupported version {raw.get('version')!r}; expected {SCENE_VERSION}")
    token = reader.string(raw, "token", "")
    frame_interval_s = reader.number(reader.get(raw, "frame_interval_s", ""), "frame_interval_s")
    if frame_interval_s <= 0:
        raise reader.fail("frame_interval_s", "must be positive")
    current_index = reader.integer(reader.get(raw, "current_index", ""), "current_index")
    raw_frames = reader.get(raw, "frames", "")
    if not isinstance(raw_frames, list):
        raise reader.fail("frames", "expected a list")
    if current_index < 0 or len(raw_frames) < current_index + FUTURE_FRAMES + 1:
        raise reader.fail(
            "frames",
            f"{len(raw_frames)} frames with current_index {current_index}; "
            f"need at least current_index + {FUTURE_FRAMES + 1}",
        )
    frames = tuple(_read_frame(reader, frame, f"frames[{i}]") for i, frame in enumerate(raw_frames))
    for index in range(1, len(frames)):
        if frames[index].timestamp_us <= frames[index - 1].timestamp_us:
            raise reader.fail(f"frames[{index}].timestamp_us", "timestamps must increase")
    if frames[current_index].token != token:
        raise reader.fail(
            "token", f"{token!r} differs from the current frame's token {frames[current_index].token!r}"
        )
    return Scene(
        token=token,
        log_name=reader.string(raw, "log_name", ""),
        map_name=reader.string(raw, "map_name", ""),
        frame_interval_s=frame_interval_s,
        current_index=current_index,
        frames=frames,
        map=_read_map(reader, reader.get(raw, "map", "")),
        content_hash=content_hash,
    )


def _decompress(data: bytes, path: Path) -> bytes:
    if not path.name.endswith(".gz"):
        return data
    import gzip  # here: scoring from a warm cache reads no scene

    try:
        return gzip.decompress(data)
    except (OSError, EOFError) as error:
        raise SceneFormatError(f"{path}: (file): not a valid gzip file ({error})") from None


def _parse_json(data: bytes, path: Path) -> Any:
    """Return the JSON document `data` as the standard library reads it (`read_json`)."""
    try:
        return read_json(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise SceneFormatError(f"{path}: (file): not valid JSON ({error})") from None


def scene_file_hash(path: Path) -> str:
    """Return the sha256 of a scene file as stored: the cache key, checked on every scoring.

    A process remembers a file's hash while the file's status (device, inode, size, modification and change
    times) stays the same, as git's index does: a worker scores the same split chunk after chunk and entry
    after entry, and reading and hashing each scene was 4% of scoring a token. A file changed in the last
    RACY_LISTING_S is hashed afresh, as `scene_paths` lists such a directory afresh.
    """
    status = path.stat()
    if time.time_ns() - max(status.st_mtime_ns, status.st_ctime_ns) < RACY_LISTING_S * 1e9:
        return _file_hash(path)
    signature = (status.st_dev, status.st_ino, status.st_size, status.st_mtime_ns, status.st_ctime_ns)
    return _remembered_hash(path, signature)


def _file_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@lru_cache(maxsize=1 << 16)  # a navtest-size split is 12,000 scenes
def _remembered_hash(path: Path, signature: tuple[int, ...]) -> str:
    """Return `_file_hash(path)`, remembered for the path while its file's status is `signature`."""
    return _file_hash(path)


def load_scene(path: Path | str) -> Scene:
    """Return the validated scene stored at `path`; its content hash is the sha256 of the file as stored."""
    path = Path(path)
    stored = path.read_bytes()
    # The decoded document is a tree of lists and dicts: dropped before the collector resumes, never walked.
    with collector_paused():
        raw = _parse_json(_decompress(stored, path), path)
        scene = parse_scene(raw, str(path), hashlib.sha256(stored).hexdigest())
        del raw
    expected_stem = path.name.removesuffix(".gz").removesuffix(".json")
    if scene.token != expected_stem:
        raise SceneFormatError(f"{path}: token: {scene.token!r} differs from the file name {expected_stem!r}")
    return scene


def scene_start(path: Path) -> tuple[str, int]:
    """Return a scene file's log name and its current frame's timestamp (us), without building the scene: where
    the scene sits in its log, which v2.2's two-frame comfort pairs by (`scorer.evaluate.pairing_contexts`)."""
    raw = _parse_json(_decompress(path.read_bytes(), path), path)
    reader = _Reader(str(path))
    frames = reader.get(raw, "frames", "")
    index = reader.integer(reader.get(raw, "current_index", ""), "current_index")
    if not isinstance(frames, list) or not 0 <= index < len(frames):
        raise reader.fail("frames", f"no frame at current_index {index}")
    where = f"frames[{index}]"
    return reader.string(raw, "log_name", ""), reader.integer(
        reader.get(frames[index], "timestamp_us", where), f"{where}.timestamp_us"
    )


def scene_paths(split_dir: Path | str) -> dict[str, Path]:
    """Return token -> scene file of a split directory (`<split>/scenes/<token>.json[.gz]`), sorted by token.

    A worker asks for every chunk and seed: the listing is kept while the directory's modification time,
    which every file added, removed or renamed moves, stays the same (12,000 names cost 65-155 ms to list).
    A directory modified in the last RACY_LISTING_S is listed afresh, as git treats a racily clean file: the
    clock ticks coarser than a file is written, so two changes can share a modification time.
    """
    scenes_dir = Path(split_dir) / "scenes"
    try:
        status = scenes_dir.stat()
    except (FileNotFoundError, NotADirectoryError):  # other errors (a name too long) say what is wrong
        status = None
    if status is None or not stat.S_ISDIR(status.st_mode):
        raise SceneFormatError(f"{split_dir}: no scenes/ directory")
    working_dir = None if scenes_dir.is_absolute() else Path.cwd()  # what a relative path names
    if time.time_ns() - status.st_mtime_ns < RACY_LISTING_S * 1e9:
        return _listing.__wrapped__(scenes_dir, working_dir, status.st_mtime_ns)
    return dict(_listing(scenes_dir, working_dir, status.st_mtime_ns))


RACY_LISTING_S = 2.0


@lru_cache(maxsize=8)
def _listing(scenes_dir: Path, working_dir: Path | None, modified_ns: int) -> dict[str, Path]:
    """Return token -> scene file of `scenes_dir` (relative to `working_dir` if not absolute) as listed when it
    was last modified at `modified_ns`."""
    paths: dict[str, Path] = {}
    for path in sorted(scenes_dir.iterdir()):
        if not (path.name.endswith(".json") or path.name.endswith(".json.gz")):
            continue
        token = path.name.removesuffix(".gz").removesuffix(".json")
        if token in paths:
            raise SceneFormatError(f"{path}: token {token!r} stored twice in {scenes_dir}")
        paths[token] = path
    return dict(sorted(paths.items()))


def iter_scenes(split_dir: Path | str) -> Iterator[Scene]:
    """Yield the validated scenes of a split in token order."""
    for path in scene_paths(split_dir).values():
        yield load_scene(path)
