"""Scene reader: the reference scenes load, and every broken rule names the file and the field."""

from __future__ import annotations

import copy
import gzip
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import scorer.scene as scene_module
from scorer.scene import SceneFormatError, iter_scenes, load_scene, scene_paths

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
TOKEN = "05ef979906eefe4a"


def _raw_scene() -> dict[str, Any]:
    return json.loads(gzip.decompress((REFERENCE / "scenes" / f"{TOKEN}.json.gz").read_bytes()))


def _write(tmp_path: Path, raw: dict[str, Any], name: str = TOKEN) -> Path:
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(raw))
    return path


def test_reference_split_loads_with_float32_dynamics() -> None:
    scenes = list(iter_scenes(REFERENCE))
    assert len(scenes) == 40
    assert [scene.token for scene in scenes] == sorted(scene.token for scene in scenes)
    raw = _raw_scene()["frames"][3]["ego"]
    ego = next(scene for scene in scenes if scene.token == TOKEN).current_frame.ego
    assert ego.x == raw["x"]  # poses stay float64
    assert ego.vx == float(np.float32(raw["vx"])) and ego.vx != raw["vx"]


def test_json_and_gzip_give_the_same_scene(tmp_path: Path) -> None:
    plain = load_scene(_write(tmp_path, _raw_scene()))
    packed = load_scene(REFERENCE / "scenes" / f"{TOKEN}.json.gz")
    assert plain.current_frame.ego == packed.current_frame.ego
    assert np.array_equal(plain.current_frame.boxes, packed.current_frame.boxes)
    assert plain.content_hash != packed.content_hash  # the key is the stored file


def _set(path: list[Any], value: Any) -> Callable[[dict[str, Any]], None]:
    def mutate(raw: dict[str, Any]) -> None:
        target = raw
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value

    return mutate


def _delete(path: list[Any]) -> Callable[[dict[str, Any]], None]:
    def mutate(raw: dict[str, Any]) -> None:
        target = raw
        for key in path[:-1]:
            target = target[key]
        del target[path[-1]]

    return mutate


BROKEN = [
    (_set(["format"], "other"), "format"),
    (_set(["version"], 2), "version"),
    (_delete(["frames", 3, "ego", "vx"]), "frames[3].ego.vx"),
    (_set(["frames", 2, "ego", "heading"], 4.0), "frames[2].ego.heading"),
    (_set(["frames", 3, "objects", 0, "box"], [1.0, 2.0, 3.0]), "frames[3].objects[0].box"),
    (_set(["frames", 3, "objects", 0, "category"], "truck"), "frames[3].objects[0].category"),
    (_set(["frames", 3, "objects", 0, "velocity"], [float("nan"), 0.0]), "frames[3].objects[0].velocity"),
    (_set(["frames", 3, "timestamp_us"], 1.5), "frames[3].timestamp_us"),
    (_set(["frames", 4, "timestamp_us"], 0), "frames[4].timestamp_us"),
    (_set(["frames", 3, "driving_command"], [0, 1, 0]), "frames[3].driving_command"),
    (_set(["frames", 3, "route_roadblocks"], ["abc"]), "frames[3].route_roadblocks"),
    (_set(["frames", 3, "route_roadblocks"], ["12", "012"]), "frames[3].route_roadblocks"),
    (_set(["frames", 3, "objects", 1, "track"], ""), "frames[3].objects[1].track"),
    (_set(["frames", 3, "traffic_lights"], [["303236", "red"]]), "frames[3].traffic_lights[0]"),
    (_set(["current_index"], 5), "frames"),
    (_set(["token"], "ffffffffffffffff"), "token"),
    (_set(["map", "lanes", 0, "baseline"], [[1.0, 2.0]]), "map.lanes[0].baseline"),
    (_set(["map", "lanes", 0, "polygon"], [[1.0, 2.0], [3.0, 4.0]]), "map.lanes[0].polygon"),
    (_set(["map", "lanes", 0, "polygon"], [[1.0, 2.0], [3.0, 4.0, 5.0], [6.0, 7.0]]), "map.lanes[0].polygon"),
    (_set(["map", "lanes", 0, "polygon"], [[[1.0, 2.0], [3.0, 4.0]]] * 3), "map.lanes[0].polygon"),
    (_set(["map", "lanes", 0, "baseline"], ["12", "34"]), "map.lanes[0].baseline"),
    (_set(["map", "lanes", 0, "baseline"], [{"1": 0, "2": 0}, {"3": 0, "4": 0}]), "map.lanes[0].baseline"),
    (_set(["map", "lanes", 0, "speed_limit_mps"], -1), "map.lanes[0].speed_limit_mps"),
    (_set(["map", "lanes", 0, "outgoing"], []), "map.lanes[0].outgoing"),
    (_set(["map", "lane_connectors", 0, "incoming"], ["1", "2"]), "map.lane_connectors[0].incoming"),
    (_set(["map", "roadblocks", 0, "lanes"], []), "map.roadblocks[0].lanes"),
    (_set(["map", "roadblocks", 1, "outgoing"], ["007"]), "map.roadblocks[1].outgoing"),
    (_set(["map", "lanes", 1, "incoming"], "12"), "map.lanes[1].incoming"),
    (_set(["map", "lane_connectors", 0, "outgoing"], [12]), "map.lane_connectors[0].outgoing"),
    (_set(["map", "hovercraft_lanes"], []), "map"),
    (_delete(["map", "roadblocks"]), "map.roadblocks"),
]


@pytest.mark.parametrize(("mutate", "field"), BROKEN)
def test_broken_rule_names_file_and_field(
    tmp_path: Path, mutate: Callable[[dict[str, Any]], None], field: str
) -> None:
    raw = copy.deepcopy(_raw_scene())
    mutate(raw)
    path = _write(tmp_path, raw)
    with pytest.raises(SceneFormatError) as error:
        load_scene(path)
    assert str(error.value).startswith(f"{path}: {field}:"), str(error.value)


def test_objects_read_in_one_call_equal_those_read_one_by_one(monkeypatch: pytest.MonkeyPatch) -> None:
    path = REFERENCE / "scenes" / f"{TOKEN}.json.gz"
    together = load_scene(path)
    monkeypatch.setattr(scene_module, "_valid_object_columns", lambda raw_objects: None)
    alone = load_scene(path)
    for first, second in zip(together.frames, alone.frames, strict=True):
        assert first.boxes.tobytes() == second.boxes.tobytes() and first.boxes.shape == second.boxes.shape
        assert first.velocities.tobytes() == second.velocities.tobytes()


def test_the_first_invalid_object_field_is_named_in_file_order(tmp_path: Path) -> None:
    raw = _raw_scene()
    objects = raw["frames"][3]["objects"]
    objects[0]["box"][4] = 0.0  # a zero width, found before the next object's category
    objects[1]["category"] = "truck"
    path = _write(tmp_path, raw)
    with pytest.raises(SceneFormatError, match=r"frames\[3\]\.objects\[0\]\.box: length and width"):
        load_scene(path)


def test_map_point_lists_read_per_layer_equal_those_read_one_by_one(monkeypatch: pytest.MonkeyPatch) -> None:
    path = REFERENCE / "scenes" / f"{TOKEN}.json.gz"
    together = load_scene(path).map
    monkeypatch.setattr(scene_module, "_valid_point_lists", lambda raw_layer, key, minimum: None)
    alone = load_scene(path).map
    for layer in scene_module.MapExcerpt._fields:
        first, second = getattr(together, layer), getattr(alone, layer)
        assert [item.polygon.wkb for item in first] == [item.polygon.wkb for item in second]
        if layer in ("lanes", "lane_connectors"):
            assert [lane.baseline.tobytes() for lane in first] == [lane.baseline.tobytes() for lane in second]
            assert all(lane.baseline.shape == (len(lane.baseline), 2) for lane in first)
    assert sum(len(getattr(together, layer)) for layer in scene_module.AREA_LAYERS) > 0


def test_the_first_invalid_map_field_is_named_in_file_order(tmp_path: Path) -> None:
    raw = _raw_scene()
    lanes = raw["map"]["lanes"]
    lanes[0]["polygon"] = lanes[0]["polygon"][:2]  # a ring too short, found before the next lane's id
    lanes[1]["id"] = "01"
    lanes[1]["baseline"] = [[0.0, "x"]]
    path = _write(tmp_path, raw)
    with pytest.raises(SceneFormatError, match=r"map\.lanes\[0\]\.polygon: a polygon needs at least 3"):
        load_scene(path)


def test_duplicate_map_id_is_rejected(tmp_path: Path) -> None:
    raw = _raw_scene()
    raw["map"]["crosswalks"].append(copy.deepcopy(raw["map"]["crosswalks"][0]))
    path = _write(tmp_path, raw)
    with pytest.raises(SceneFormatError, match=r"map\.crosswalks\[\d+\]\.id: duplicate id"):
        load_scene(path)


def test_file_level_errors(tmp_path: Path) -> None:
    bad_json = tmp_path / f"{TOKEN}.json"
    bad_json.write_text("{")
    with pytest.raises(SceneFormatError, match="not valid JSON"):
        load_scene(bad_json)
    bad_gzip = tmp_path / f"{TOKEN}.json.gz"
    bad_gzip.write_bytes(b"not gzip")
    with pytest.raises(SceneFormatError, match="not a valid gzip file"):
        load_scene(bad_gzip)
    with pytest.raises(SceneFormatError, match="differs from the file name"):
        load_scene(_write(tmp_path, _raw_scene(), name="0000000000000000"))


def test_split_without_scenes_dir(tmp_path: Path) -> None:
    with pytest.raises(SceneFormatError, match="no scenes/ directory"):
        scene_paths(tmp_path)


def test_a_split_listing_follows_the_files_added_removed_and_renamed(tmp_path: Path) -> None:
    """The listing is kept between calls (a worker asks for every chunk and seed) only while the directory is
    unchanged: every scene added, removed or renamed shows at once."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    (scenes / "a.json.gz").write_bytes(b"")
    assert list(scene_paths(tmp_path)) == ["a"]
    listing = scene_paths(tmp_path)
    listing["x"] = scenes / "x.json"  # a caller's change stays its own
    (scenes / "b.json").write_bytes(b"")
    assert list(scene_paths(tmp_path)) == ["a", "b"]
    (scenes / "a.json.gz").rename(scenes / "c.json.gz")
    assert list(scene_paths(tmp_path)) == ["b", "c"]
    (scenes / "b.json").unlink()
    assert list(scene_paths(tmp_path)) == ["c"]

    # Modified long ago, the listing is kept: a file slipped in under the same modification time stays unseen
    # (what proves the cache), and any later change shows.
    os.utime(scenes, ns=(10**18, 10**18))
    assert list(scene_paths(tmp_path)) == ["c"]
    (scenes / "d.json").write_bytes(b"")
    os.utime(scenes, ns=(10**18, 10**18))
    assert list(scene_paths(tmp_path)) == ["c"]
    os.utime(scenes, ns=(10**18 + 1, 10**18 + 1))
    assert list(scene_paths(tmp_path)) == ["c", "d"]


def test_a_scene_hash_is_remembered_only_while_its_file_is_unchanged(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A worker hashes each scene once per process, and any change to the file, even one that keeps its size
    and modification time, gives its new hash at once; a file changed in the last seconds is read every time."""
    reads: list[Path] = []
    file_hash = scene_module._file_hash
    monkeypatch.setattr(scene_module, "_file_hash", lambda path: reads.append(path) or file_hash(path))
    scene_module._remembered_hash.cache_clear()
    path = tmp_path / "a.json"
    path.write_bytes(b'{"token": "a"}')
    first = scene_module.scene_file_hash(path)
    assert scene_module.scene_file_hash(path) == first and len(reads) == 2  # changed just now: read again

    monkeypatch.setattr(scene_module, "RACY_LISTING_S", -1.0)  # as if changed long ago
    assert [scene_module.scene_file_hash(path) for _ in range(3)] == [first] * 3 and len(reads) == 3
    modified = path.stat().st_mtime_ns
    path.write_bytes(b'{"token": "b"}')  # the same size
    os.utime(path, ns=(modified, modified))  # and modification time; the change time moves
    second = scene_module.scene_file_hash(path)
    assert second != first and second == file_hash(path) and len(reads) == 4


def test_map_id_lists_read_per_layer_equal_those_read_one_by_one(monkeypatch: pytest.MonkeyPatch) -> None:
    path = REFERENCE / "scenes" / f"{TOKEN}.json.gz"
    together = load_scene(path).map
    monkeypatch.setattr(scene_module, "_valid_id_lists", lambda raw_layer, keys: None)
    alone = load_scene(path).map
    for layer in ("lanes", "lane_connectors", "roadblocks", "roadblock_connectors"):
        for first, second in zip(getattr(together, layer), getattr(alone, layer), strict=True):
            keys = ("id", "incoming", "outgoing") + (("lanes",) if hasattr(first, "lanes") else ())
            assert [getattr(first, key) for key in keys] == [getattr(second, key) for key in keys]
            assert all(type(getattr(first, key)) is tuple for key in keys[1:])
