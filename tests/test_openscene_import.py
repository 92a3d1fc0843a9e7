"""`navsim-lb import-openscene`: scene files from log pickles and GeoPackages, report, resumability, CLI."""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import pytest
import typer
from openscene_builders import (
    LOCATION,
    TURN_CONNECTOR,
    connector_id,
    frame_token,
    log_frame,
    road_frames,
    roadblock_id,
    write_log,
    write_maps,
    write_road_log,
)
from typer.testing import CliRunner

from navsim_lb.openscene_cli import register
from scorer.baselines import human
from scorer.openscene.excerpt import build_excerpt, excerpt_to_json
from scorer.openscene.frames import convert_frame, ego_pose, route_roadblocks, vehicle_centres
from scorer.openscene.gpkg import gpkg_path, load_map_tables
from scorer.openscene.importer import (
    JOURNAL_NAME,
    REPORT_NAME,
    ImportSettings,
    SceneFilter,
    import_logs,
    read_scene_filter,
    scene_path,
)
from scorer.openscene.log_pickle import load_log
from scorer.scene import load_scene, scene_paths

MISMATCH_FRAME = 10  # its stored command says "left" on a straight road
NO_ROUTE_FRAME = 25


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("openscene")
    write_maps(root / "maps")
    truth = road_frames()
    truth[MISMATCH_FRAME].command = [1, 0, 0, 0]
    assert truth[NO_ROUTE_FRAME].route == []
    log_path = root / "logs" / "2021.05.12.22.00.38_veh-35_01008_01518.pkl"
    write_log(log_path, [log_frame(frame, log_path.stem) for frame in truth])
    return {"root": root, "logs": root / "logs", "maps": root / "maps", "log": log_path}


@pytest.fixture(scope="module")
def imported(data: dict[str, Path]) -> tuple[Path, dict]:
    out = data["root"] / "split"
    report = import_logs(data["logs"], ImportSettings(data["maps"], out))
    return out, report


def test_every_window_with_a_route_becomes_a_valid_scene(imported) -> None:
    out, report = imported
    expected = [frame_token(1, k) for k in range(3, 30) if k != NO_ROUTE_FRAME]
    assert list(scene_paths(out)) == expected
    assert report["this_run"] == {"written": 26, "present": 0, "skipped": 1}
    assert report["scenes"] == 26
    assert report["skipped"] == [
        {
            "token": frame_token(1, NO_ROUTE_FRAME),
            "log": "2021.05.12.22.00.38_veh-35_01008_01518",
            "reason": "no route at the current frame (roadblock_ids is empty)",
        }
    ]
    for path in scene_paths(out).values():
        scene = load_scene(path)
        assert scene.current_index == 3 and len(scene.frames) == 14 and scene.map_name == LOCATION


def test_scene_content_is_the_converted_window_and_its_excerpt(data, imported) -> None:
    out, _ = imported
    frames = load_log(data["log"])
    tables = load_map_tables(gpkg_path(data["maps"], LOCATION), LOCATION)
    token = frame_token(1, 12)
    raw = json.loads(gzip.decompress(scene_path(out, token).read_bytes()))
    window = frames[9:23]
    expected_frames = [convert_frame(frame) for frame in window]
    assert [f["token"] for f in raw["frames"]] == [f["token"] for f in expected_frames]
    for written, expected in zip(raw["frames"], expected_frames, strict=True):
        assert written == expected  # every field, floats bit for bit (the stored commands are all one-hot)
    current = window[3]
    vehicles = vehicle_centres(expected_frames[3]["objects"])
    excerpt = build_excerpt(tables, ego_pose(current), route_roadblocks(current), vehicles)
    assert raw["map"] == json.loads(json.dumps(excerpt_to_json(excerpt.map)))
    assert (raw["token"], raw["log_name"], raw["frame_interval_s"]) == (token, data["log"].stem, 0.5)


def test_imported_scenes_score(data, tmp_path: Path) -> None:
    from scorer.evaluate import score_tokens

    # A steady drive (the default fixture's swaying yaw is for the conversion tests, not for driving).
    write_road_log(tmp_path / "logs", yaw_amplitude=0.0)
    out = tmp_path / "split"
    import_logs(tmp_path / "logs", ImportSettings(data["maps"], out))
    # The recorded future in the frame of the current ego (the human agent): it keeps its lane on a clear road.
    recorded = {token: human(load_scene(path)) for token, path in scene_paths(out).items()}
    results = score_tokens(out, tmp_path / "cache", recorded, "v1.1")
    assert len(results) == 26
    assert all(result.valid for result in results), [r.error for r in results if not r.valid]
    metrics = {(r.metrics["no_at_fault_collisions"], r.metrics["drivable_area_compliance"]) for r in results}
    assert metrics == {(1.0, 1.0)}


def test_report_lists_command_mismatches_and_map_warnings(imported) -> None:
    out, report = imported
    mismatches = report["command_mismatches"]
    assert mismatches == [
        {
            "token": frame_token(1, MISMATCH_FRAME),
            "log": "2021.05.12.22.00.38_veh-35_01008_01518",
            "stored": [1, 0, 0, 0],
            "computed": [0, 1, 0, 0],
        }
    ]
    # Scenes near the junction carry its intersection, whose hole format v1 cannot store.
    assert any("intersections 7000: 1 hole(s) dropped" in w["message"] for w in report["warnings"])
    assert json.loads((out / REPORT_NAME).read_text()) == report


def test_files_are_deterministic(data, imported, tmp_path: Path) -> None:
    out, _ = imported
    tokens = (frame_token(1, 4),)
    import_logs(data["logs"], ImportSettings(data["maps"], tmp_path), SceneFilter(tokens=tokens))
    assert scene_path(tmp_path, tokens[0]).read_bytes() == scene_path(out, tokens[0]).read_bytes()


def test_import_resumes_where_it_stopped(data, tmp_path: Path) -> None:
    out = tmp_path / "split"
    settings = ImportSettings(data["maps"], out)
    import_logs(data["logs"], settings)
    lost = [frame_token(1, 5), frame_token(1, 20)]
    for token in lost:
        scene_path(out, token).unlink()
    before = {token: path.stat().st_mtime_ns for token, path in scene_paths(out).items()}
    report = import_logs(data["logs"], settings)
    assert report["this_run"] == {"written": 2, "present": 24, "skipped": 1}
    assert sorted(set(scene_paths(out)) - set(before)) == lost
    assert all(scene_paths(out)[token].stat().st_mtime_ns == mtime for token, mtime in before.items())
    # The report describes the split, not the run: earlier mismatches are still listed.
    assert report["scenes"] == 26 and len(report["command_mismatches"]) == 1 and len(report["skipped"]) == 1
    assert len((out / JOURNAL_NAME).read_text().splitlines()) == 2 * 27


def test_token_list_reports_why_each_token_is_skipped(data, tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    shutil.copytree(data["logs"], logs)
    test_mode = road_frames(log_index=2, count=16)
    write_log(logs / "test_mode.pkl", [log_frame(frame, "test_mode", test_mode=True) for frame in test_mode])
    odd = road_frames(log_index=3, count=16)
    frames = [log_frame(frame, "odd") for frame in odd]
    frames[8]["anns"]["gt_names"][0] = "animal"
    for frame in frames[3:5]:
        frame["map_location"] = "mars"
    write_log(logs / "odd.pkl", frames)
    (logs / "broken.pkl").write_bytes(b"garbage")
    wanted = {
        frame_token(1, 12): None,
        frame_token(1, 1): "only 1 frame(s) before it in the log; a scene needs 3",
        frame_token(1, 31): "only 8 frame(s) after it in the log; a scene needs 10",
        frame_token(1, NO_ROUTE_FRAME): "no route at the current frame (roadblock_ids is empty)",
        "00000000deadbeef": f"not found in any log of {logs} (1 log(s) unreadable)",
        frame_token(2, 4): f"FrameError: frame {frame_token(2, 1)}: anns: missing key",
        frame_token(3, 4): "MapFormatError: unknown map location 'mars'",
        frame_token(
            3, 5
        ): f"FrameError: frame {frame_token(3, 8)}: anns.gt_names: unknown class(es) ['animal']",
    }
    token_file = tmp_path / "tokens.yaml"
    token_file.write_text(
        "# scene filter\nnum_history_frames: 4\ntokens:\n" + "".join(f"  - '{t}'\n" for t in wanted)
    )
    assert read_scene_filter(token_file) == SceneFilter(tokens=tuple(wanted))
    report = import_logs(
        logs, ImportSettings(data["maps"], tmp_path / "split"), read_scene_filter(token_file), workers=2
    )
    assert list(scene_paths(tmp_path / "split")) == [frame_token(1, 12)]
    reasons = {entry["token"]: entry["reason"] for entry in report["skipped"]}
    assert set(reasons) == {token for token, reason in wanted.items() if reason}
    for token, reason in reasons.items():
        assert reason.startswith(wanted[token]), (token, reason)
    assert [failure["log"] for failure in report["failed_logs"]] == ["broken"]


def test_token_list_rejects_garbage(tmp_path: Path) -> None:
    path = tmp_path / "tokens.txt"
    path.write_text("0123456789abcdef\n# a comment\nnot-a-token\n")
    with pytest.raises(ValueError, match=r"tokens.txt:3: 'not-a-token' is not a token"):
        read_scene_filter(path)
    navsim = tmp_path / "navtest.yaml"
    navsim.write_text("_target_: navsim.common.dataclasses.SceneFilter\ntokens: [0123456789abcdef, nope]\n")
    with pytest.raises(ValueError, match=r"navtest.yaml: tokens\[1\]: 'nope' is not a token"):
        read_scene_filter(navsim)
    navsim.write_text("num_history_frames: 4\n")
    with pytest.raises(ValueError, match="neither tokens nor log_names"):
        read_scene_filter(navsim)


# NAVSIM's scene filters (e.g. navtest.yaml) name logs, tokens, or both, beside keys of their own.
NAVSIM_FILTER = """_target_: navsim.common.dataclasses.SceneFilter
_convert_: 'all'
num_history_frames: 4
num_future_frames: 10
frame_interval: 1
has_route: true
max_scenes: null
"""


@pytest.mark.parametrize("layout", ["log_names", "tokens", "both"])
def test_navsim_scene_filters_select_logs_tokens_or_both(data, tmp_path: Path, layout: str) -> None:
    logs = tmp_path / "logs"
    shutil.copytree(data["logs"], logs)
    write_log(
        logs / "second.pkl", [log_frame(frame, "second") for frame in road_frames(log_index=6, count=16)]
    )
    names = sorted(path.stem for path in logs.glob("*.pkl"))
    every = set(scene_paths(_imported(data, logs, tmp_path / "every", None)))
    first_log = set(
        scene_paths(_imported(data, logs, tmp_path / "first", SceneFilter(log_names=(names[0],))))
    )
    assert first_log and first_log < every  # the filter keeps one log's scenes, and only those
    token = min(first_log)
    lines = {
        "log_names": f"log_names:\n  - {names[0]}\n  - not_a_log\n",
        "tokens": f"tokens:\n  - '{token}'\n",
        "both": f"log_names: [{names[1]}]\ntokens: ['{token}']\n",
    }[layout]
    path = tmp_path / "navtest.yaml"
    path.write_text(NAVSIM_FILTER + lines)
    report = import_logs(logs, ImportSettings(data["maps"], tmp_path / "split"), read_scene_filter(path))
    split = tmp_path / "split"
    imported = set(scene_paths(split)) if (split / "scenes").is_dir() else set()
    if layout == "log_names":
        assert imported == first_log
        assert report["failed_logs"] == [
            {"log": "not_a_log", "reason": f"named by the scene filter but not in {logs}"}
        ]
    elif layout == "tokens":
        assert imported == {token}
    else:  # the token lies in the first log and the filter names only the second: nothing matches both
        assert imported == set()
        assert [entry["token"] for entry in report["skipped"]] == [token]


def _imported(data, logs: Path, out: Path, scene_filter: SceneFilter | None) -> Path:
    import_logs(logs, ImportSettings(data["maps"], out), scene_filter)
    return out


def test_missing_commands_are_computed_from_the_route(tmp_path: Path, data) -> None:
    # An ego approaching roadblock 22's left turn, whose log has no driving commands.
    truth = road_frames(log_index=4, count=20, start_x=1040.0, with_commands=False)
    route = [str(b) for b in (roadblock_id(21), connector_id(21), roadblock_id(22), TURN_CONNECTOR, 1600)]
    for frame in truth:
        frame.route = route
        frame.y += 3.5  # the left lane
    write_log(tmp_path / "logs" / "turn.pkl", [log_frame(frame, "turn") for frame in truth])
    report = import_logs(tmp_path / "logs", ImportSettings(data["maps"], tmp_path / "split"))
    scenes = {token: load_scene(path) for token, path in scene_paths(tmp_path / "split").items()}
    assert len(scenes) == 7 and report["command_mismatches"] == []
    first = scenes[frame_token(4, 3)]
    # Ego x = 1040 + 5 k; the turn starts at x = 1140 and rises 2 m within its first 5 m, so the point
    # 20 m ahead is 2 m or more to the left from x = 1130 (k = 18) on.
    assert [frame.driving_command for frame in first.frames] == [(0, 1, 0, 0)] * 14
    last = scenes[frame_token(4, 9)]
    assert [frame.driving_command for frame in last.frames] == [(0, 1, 0, 0)] * 12 + [(1, 0, 0, 0)] * 2
    assert {entry["frames"] for entry in report["computed_commands"]} == {14}


def test_cli_imports_and_reports(data, tmp_path: Path) -> None:
    app = typer.Typer()
    register(app)
    app.command("noop")(lambda: None)  # keeps typer in multi-command mode
    result = CliRunner().invoke(
        app,
        [
            "import-openscene",
            "--logs",
            str(data["logs"]),
            "--maps",
            str(data["maps"]),
            "--workers",
            "1",
            str(tmp_path / "split"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "26 scenes written, 0 already present, 1 skipped" in " ".join(result.output.split())
    assert (tmp_path / "split" / REPORT_NAME).is_file()
    result = CliRunner().invoke(
        app,
        [
            "import-openscene",
            "--logs",
            str(tmp_path / "none"),
            "--maps",
            str(data["maps"]),
            str(tmp_path / "x"),
        ],
    )
    assert result.exit_code == 2 and "not a directory" in " ".join(result.output.split())


def test_navhard_windows_need_8_future_frames_and_hold_the_last(data, tmp_path: Path) -> None:
    # navhard's scene filter asks for 8 future frames; the format keeps 10, so the last is held.
    tokens = (frame_token(1, 30), frame_token(1, 31), frame_token(1, 32))
    settings = ImportSettings(data["maps"], tmp_path / "split", future_frames=8)
    report = import_logs(data["logs"], settings, SceneFilter(tokens=tokens))
    assert list(scene_paths(tmp_path / "split")) == list(tokens[:2])
    assert [(entry["token"], entry["reason"]) for entry in report["skipped"]] == [
        (tokens[2], "only 7 frame(s) after it in the log; a scene needs 8")
    ]
    raw = json.loads(gzip.decompress(scene_path(tmp_path / "split", tokens[1]).read_bytes()))
    log = load_log(data["log"])
    assert raw["frames"][:12] == [convert_frame(frame) for frame in log[28:40]]
    last = raw["frames"][11]
    for step, frame in enumerate(raw["frames"][12:], start=1):
        assert frame == {
            **last,
            "token": f"{last['token']}+{step}",
            "timestamp_us": last["timestamp_us"] + step * 500_000,
        }
    held = {w["token"]: w["message"] for w in report["warnings"] if "future" in w["message"]}
    assert held == {
        token: f"{count} future frames, the last held to +10 (v2 observes 8; only v1.x versions would read the held ones)"
        for token, count in zip(tokens, (9, 8), strict=False)
    }
