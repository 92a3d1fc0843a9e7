"""Round trip of the 40 reference scenes through the upstream formats and the importer.

Each reference scene is written as NAVSIM would have read it (an OpenScene log of its 14 frames,
made with the generator's forward transforms, and a GeoPackage of its map in the projected system),
imported again, compared field by field with the original, and scored against the official results.
"""

from __future__ import annotations

import gzip
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from devkit_kernels import devkit_tolerance
from openscene_builders import exact_yaw_quaternion, map_tables, write_gpkg, write_log

from scorer.geometry import rear_axle_round_trip
from scorer.openscene.importer import ImportSettings, SceneFilter, import_logs, scene_path
from scorer.scene import load_scene

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
SCENES = sorted((REFERENCE / "scenes").glob("*.json.gz"))
UTM = 32611  # the synthetic maps are stored in their projected system (no reprojection)


def log_frames(raw: dict[str, Any]) -> list[dict[str, Any]]:
    """Return OpenScene frame dicts of a scene's frames, boxes and velocities rotated back into the ego frame."""
    frames = []
    for frame in raw["frames"]:
        ego = frame["ego"]
        heading = ego["heading"]
        rear_x, rear_y = rear_axle_round_trip(ego["x"], ego["y"], heading)
        cos, sin = math.cos(heading), math.sin(heading)
        boxes = np.array([obj["box"] for obj in frame["objects"]], dtype=np.float64).reshape(-1, 7)
        dx, dy = boxes[:, 0] - rear_x, boxes[:, 1] - rear_y
        local = boxes.copy()
        local[:, 0], local[:, 1] = dx * cos + dy * sin, -dx * sin + dy * cos
        local[:, 6] = boxes[:, 6] - heading  # unwrapped, as the generator leaves it
        vx, vy = np.array([obj["velocity"] for obj in frame["objects"]], dtype=np.float64).reshape(-1, 2).T
        frames.append(
            {
                "token": frame["token"],
                "timestamp": frame["timestamp_us"],
                "log_name": raw["log_name"],
                "scene_token": "0" * 16,
                "map_location": raw["map_name"],
                "roadblock_ids": list(frame["route_roadblocks"]),
                "traffic_lights": [(int(connector), is_red) for connector, is_red in frame["traffic_lights"]],
                "ego2global_translation": np.array([ego["x"], ego["y"], 0.0]),
                "ego2global_rotation": np.array(exact_yaw_quaternion(heading)),
                "ego_dynamic_state": [ego["vx"], ego["vy"], ego["ax"], ego["ay"]],
                "driving_command": np.array(frame["driving_command"]),
                "anns": {
                    "gt_boxes": local,
                    "gt_names": np.array([obj["category"] for obj in frame["objects"]]),
                    "gt_velocity_3d": np.column_stack(
                        [vx * cos + vy * sin, -vx * sin + vy * cos, np.zeros(len(vx))]
                    ),
                    "instance_tokens": [f"{index:016x}" for index in range(len(boxes))],
                    "track_tokens": [obj["track"] for obj in frame["objects"]],
                },
                "cams": {},
                "lidar_path": "",
            }
        )
    return frames


@pytest.fixture(scope="module")
def imported(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[dict[str, Any], Path]]:
    """Return token -> (original scene JSON, imported scene file)."""
    root = tmp_path_factory.mktemp("reference")
    result = {}
    for path in SCENES:
        raw = json.loads(gzip.decompress(path.read_bytes()))
        token = raw["token"]
        maps = root / token / "maps"
        write_gpkg(
            maps / raw["map_name"] / "1.0" / "map.gpkg",
            map_tables(raw["map"]),
            storage_epsg=UTM,
            projected=f"epsg:{UTM}",
        )
        write_log(root / token / "logs" / f"{raw['log_name']}.pkl", log_frames(raw))
        report = import_logs(
            root / token / "logs", ImportSettings(maps, root / "split"), SceneFilter(tokens=(token,))
        )
        assert report["skipped"] == [], report["skipped"]
        result[token] = (raw, scene_path(root / "split", token))
    return result


def test_all_reference_scenes_survive_the_round_trip(imported) -> None:
    assert len(imported) == 40
    for token, (raw, path) in imported.items():
        scene = load_scene(path)
        original = raw["frames"]
        for frame, expected in zip(
            json.loads(gzip.decompress(path.read_bytes()))["frames"], original, strict=True
        ):
            for key in (
                "token",
                "timestamp_us",
                "ego",
                "driving_command",
                "traffic_lights",
                "route_roadblocks",
            ):
                assert frame[key] == expected[key], (token, key)
            assert [(o["track"], o["category"]) for o in frame["objects"]] == [
                (o["track"], o["category"]) for o in expected["objects"]
            ]
            for obj, expected_obj in zip(frame["objects"], expected["objects"], strict=True):
                # The synthetic scenes were never in an ego frame: the way back costs a few ulps.
                assert obj["box"] == pytest.approx(expected_obj["box"], rel=0, abs=1e-9)
                assert obj["velocity"] == pytest.approx(expected_obj["velocity"], rel=0, abs=1e-9)
        assert scene.token == token


def test_imported_excerpts_are_subsets_holding_what_the_engine_selects(imported) -> None:
    for token, (raw, path) in imported.items():
        written = json.loads(gzip.decompress(path.read_bytes()))["map"]
        for layer, objects in written.items():
            originals = {obj["id"]: obj for obj in raw["map"].get(layer, [])}
            present = {obj["id"] for obj in objects}
            assert [obj["id"] for obj in objects] == [i for i in originals if i in present], (token, layer)
            for obj in objects:
                original = originals[obj["id"]]
                for key, value in obj.items():
                    if key in ("incoming", "outgoing", "lanes"):
                        # The map's relations; the original may also name objects it does not hold.
                        assert set(value) == {
                            i for i in original[key] if i in _layer_ids(raw["map"], layer, key)
                        }
                    else:
                        assert value == original[key], (token, layer, obj["id"], key)
        # Everything the route names is there.
        blocks = {obj["id"] for layer in ("roadblocks", "roadblock_connectors") for obj in written[layer]}
        assert set(raw["frames"][3]["route_roadblocks"]) <= blocks


def _layer_ids(raw_map: dict[str, list[dict[str, Any]]], layer: str, key: str) -> set[str]:
    """Return the ids a relation list of `layer` can name."""
    targets = {
        ("lanes", "incoming"): "lane_connectors",
        ("lanes", "outgoing"): "lane_connectors",
        ("lane_connectors", "incoming"): "lanes",
        ("lane_connectors", "outgoing"): "lanes",
        ("roadblocks", "incoming"): "roadblock_connectors",
        ("roadblocks", "outgoing"): "roadblock_connectors",
        ("roadblocks", "lanes"): "lanes",
        ("roadblock_connectors", "incoming"): "roadblocks",
        ("roadblock_connectors", "outgoing"): "roadblocks",
        ("roadblock_connectors", "lanes"): "lane_connectors",
    }
    return {obj["id"] for obj in raw_map[targets[(layer, key)]]}


SCORED_FAMILIES = ("human", "cv_straight", "swerve_left", "lane_change")


CONTINUOUS = ("ego_progress", "score")


@pytest.mark.parametrize("version", ["v1.0", "v1.1"])
def test_imported_reference_scenes_score_as_the_originals(imported, version: str, tmp_path: Path) -> None:
    """Imported scenes score bit for bit as the original scene files, and as the official devkit does."""
    from scorer.evaluate import score_tokens
    from scorer.versions import METRIC_COLUMNS

    split = next(iter(imported.values()))[1].parent.parent
    for family in SCORED_FAMILIES:
        predictions = json.loads((REFERENCE / "submissions" / f"{family}.json").read_text())["predictions"]
        poses = {token: np.array(p) for token, p in predictions.items()}
        lines = gzip.decompress(
            (REFERENCE / "expected" / f"{family}.{version}.jsonl.gz").read_bytes()
        ).splitlines()
        official = {line["token"]: line for line in map(json.loads, lines)}
        results = score_tokens(split, tmp_path / "imported", poses, version)
        originals = {r.token: r for r in score_tokens(REFERENCE, tmp_path / "original", poses, version)}
        assert len(results) == 40
        for result in results:
            assert result.valid, (family, result.token, result.error)
            assert result.metrics == originals[result.token].metrics, (family, result.token)
            for column in METRIC_COLUMNS:
                # Discrete results are exact; the engine's own last-bit differences in EP are not the importer's.
                tolerance = devkit_tolerance(1e-9) if column in CONTINUOUS else 0.0
                expected = official[result.token][column]
                assert result.metrics[column] == pytest.approx(expected, rel=0, abs=tolerance), (
                    family,
                    column,
                )
