"""NAVSIM's two-stage data through the OpenScene import, scored against the official results.

The 3 groups of the two-stage fixture (fixtures/epdms-two-stage-reactive) are written as NAVSIM holds them:
the logged frames `orig` and `prev` as one OpenScene log, the map as a GeoPackage, each synthetic pair 0 as a
5-frame roll-out pickle (prev2 = frames[:-1], now2 = frames[1:]) and every other synthetic scene as a 4-frame
`Scene.save_to_disk` pickle with extended tracks and lights, the mapping as NAVSIM's split YAML. Imported
again, every token of every group scores as the official script did, bit for bit (tests/two_stage_reference).
"""

from __future__ import annotations

import copy
import gzip
import json
import pickle
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from devkit_kernels import same_number
from openscene_builders import map_tables, write_gpkg, write_log
from synthetic_builders import EgoFrameStats, stage_one_log, synthetic_pickle, write_pickle
from two_stage_reference import (
    FAMILIES,
    group_mismatches,
    official_summary,
    official_tokens,
    token_mismatches,
)
from typer.testing import CliRunner

from navsim_lb.cli import app
from scorer.evaluate import build_split_cache
from scorer.openscene.importer import ImportSettings, scene_path
from scorer.openscene.importer import map_tables as map_tables_of
from scorer.openscene.scene_pickle import ScenePickleError, load_scene_pickle
from scorer.openscene.synthetic import SyntheticSceneError, synthetic_scenes
from scorer.openscene.two_stage_import import import_synthetic, import_two_stage, read_stage_mapping
from scorer.scene import load_scene
from scorer.submission import SubmissionMetadata, TwoStageSubmission
from scorer.two_stage.score import score_two_stage
from scorer.two_stage.split import MAPPING_FILE, TwoStageSplitError, load_two_stage_split
from scorer.versions import VersionName

FIXTURES = Path(__file__).parent / "fixtures" / "epdms-two-stage-reactive"
MAPPING: list[Any] = json.loads((FIXTURES / "two_stage.json").read_text())["reactive_all_mapping"]
VERSION = VersionName.V2_2_TWO_STAGE
runner = CliRunner()
UTM = 32611  # the fixture maps are stored in their projected system


def _read(token: str, scenes: Path) -> dict[str, Any]:
    return json.loads(gzip.decompress((scenes / f"{token}.json.gz").read_bytes()))


@cache
def _raw(token: str) -> dict[str, Any]:
    return _read(token, FIXTURES / "scenes")


@cache
def _predictions(family: str) -> dict[str, list[list[float]]]:
    with gzip.open(FIXTURES / "predictions.json.gz", "rt") as handle:
        predictions: dict[str, dict[str, list[list[float]]]] = json.load(handle)
    return predictions[family]


def write_group(
    root: Path, entry: list[Any], stats: EgoFrameStats, scenes: Path = FIXTURES / "scenes"
) -> Path:
    """Write one mapping entry (its scene files in `scenes`) in NAVSIM's forms under `root`; return the split
    YAML."""
    original, previous, pairs = entry

    @cache
    def raw_scene(token: str) -> dict[str, Any]:
        return _read(token, scenes)

    raw = raw_scene(original)
    write_gpkg(
        root / "maps" / raw["map_name"] / "1.0" / "map.gpkg",
        map_tables(raw["map"]),
        storage_epsg=UTM,
        projected=f"epsg:{UTM}",
    )
    write_log(root / "logs" / f"{raw['log_name']}.pkl", stage_one_log(raw, raw_scene(previous), stats))
    for index, (now2, prev2) in enumerate(pairs):
        if index == 0:  # the private-test form of a roll-out
            content = synthetic_pickle([raw_scene(prev2), raw_scene(now2)], previous, stats)
            write_pickle(root / "synthetic" / f"{prev2}.pkl", content)
            continue
        for token, first_stage in ((now2, original), (prev2, previous)):
            write_pickle(
                root / "synthetic" / f"{token}.pkl", synthetic_pickle([raw_scene(token)], first_stage, stats)
            )
    config = root / "navhard_two_stage.yaml"
    config.write_text(
        "defaults:\n- scene_filter: navhard_two_stage\ndata_split: test\n"
        + yaml.safe_dump({"reactive_all_mapping": [entry]})
    )
    return config


@pytest.fixture(scope="module")
def imported(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Path], EgoFrameStats]:
    """Return the imported split of each group and how exactly the ego-frame values map back."""
    root = tmp_path_factory.mktemp("two-stage")
    stats = EgoFrameStats()
    splits = []
    for index, entry in enumerate(MAPPING):
        group = root / f"group{index}"
        config = write_group(group, entry, stats)
        report = import_two_stage(
            group / "logs", group / "synthetic", config, ImportSettings(group / "maps", group / "split")
        )
        assert report["skipped"] == [] and report["failed_logs"] == [], report
        assert report["two_stage"]["written"], report["two_stage"]
        splits.append(group / "split")
    return splits, stats


def test_every_token_has_its_scene_and_the_mapping(imported) -> None:
    splits, stats = imported
    for split, entry in zip(splits, MAPPING, strict=True):
        stage = load_two_stage_split(split)
        assert [[g.original, g.previous, [list(p) for p in g.pairs]] for g in stage.groups or ()] == [entry]
        for token in stage.stage_two_tokens:
            scene = load_scene(scene_path(split, token))
            expected = load_scene(FIXTURES / "scenes" / f"{token}.json.gz")
            # A prev2 of a 5-frame roll-out has one future frame more (now2's current frame).
            assert [f.timestamp_us for f in scene.frames[:14]] == [f.timestamp_us for f in expected.frames]
            assert [f.token for f in scene.frames[:4]] == [f.token for f in expected.frames[:4]]
            assert [f.ego for f in scene.frames[:4]] == [f.ego for f in expected.frames[:4]]
            for frame, expected_frame in zip(scene.future_frames, expected.future_frames, strict=True):
                assert frame.traffic_lights == expected_frame.traffic_lights
                assert sorted(frame.tracks) == sorted(expected_frame.tracks)
    # The forward transform has an exact preimage for every position; some headings and velocities have none.
    assert stats.counts["box_xy"][1] == 0, stats.counts


@pytest.fixture(scope="module")
def caches(imported, tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    splits, _ = imported
    directories = []
    for split in splits:
        directory = tmp_path_factory.mktemp("cache")
        assert build_split_cache(split, directory, [VERSION]) == {}
        directories.append(directory)
    return directories


# The families whose IDM traces the fixture keeps run in CI; the other ten with `-m full_reference`.
TRACED = ("human", "cv_accel", "swerve_left_fast")


@pytest.mark.parametrize(
    "family",
    [
        family if family in TRACED else pytest.param(family, marks=pytest.mark.full_reference)
        for family in FAMILIES
    ],
)
def test_imported_groups_score_as_the_official_script(imported, caches, family: str) -> None:
    splits, _ = imported
    for index, (split, cache_dir, entry) in enumerate(zip(splits, caches, MAPPING, strict=True)):
        original, previous, pairs = entry
        first = [original, previous]
        second = [token for pair in pairs for token in pair]
        poses = {token: np.array(value) for token, value in _predictions(family).items()}
        submission = TwoStageSubmission(
            SubmissionMetadata(), ({t: poses[t] for t in first},), ({t: poses[t] for t in second},)
        )
        [result] = score_two_stage(split, cache_dir, submission, VERSION)
        assert token_mismatches(result, official_tokens(family)) == [], (family, original)
        assert group_mismatches(result, [official_summary(family)["groups"][index]]) == [], (family, original)


def test_the_command_line_imports_a_two_stage_split_that_scores(tmp_path: Path) -> None:
    entry = MAPPING[2]
    config = write_group(tmp_path, entry, EgoFrameStats())
    split = tmp_path / "split"
    arguments = [
        "import-openscene",
        str(split),
        "--logs",
        str(tmp_path / "logs"),
        "--maps",
        str(tmp_path / "maps"),
    ]
    result = runner.invoke(app, [*arguments, "--workers", "1", "--stage-mapping", str(config)])
    assert result.exit_code == 2 and "needs both --stage-mapping and --synthetic" in _text(result.output)
    two_stage = ["--stage-mapping", str(config), "--synthetic", str(tmp_path / "synthetic")]
    result = runner.invoke(app, [*arguments, "--workers", "1", *two_stage])
    assert result.exit_code == 0, result.output
    assert "12 scenes written" in _text(result.output) and "two-stage split: 1 groups" in _text(result.output)
    original, previous, pairs = entry
    predictions = _predictions("swerve_left_fast")
    submission = tmp_path / "submission.json"
    submission.write_text(
        json.dumps(
            {
                "format": "navsim-lb/submission-two-stage",
                "version": 1,
                "first_stage_predictions": [{token: predictions[token] for token in (original, previous)}],
                "second_stage_predictions": [{token: predictions[token] for pair in pairs for token in pair}],
            }
        )
    )
    out = tmp_path / "results.csv"
    result = runner.invoke(
        app,
        [
            "score",
            str(split),
            str(submission),
            "--version",
            VERSION,
            "--out",
            str(out),
            "--cache-dir",
            str(tmp_path / "cache"),
        ],
    )
    assert result.exit_code == 0, result.output
    rows = {line.split(",")[1]: line.split(",") for line in out.read_text().splitlines()[1:]}
    combined = official_summary("swerve_left_fast")["groups"][2]["combined"]
    assert float(rows["extended_pdm_score_combined"][-1]) == combined
    official = official_tokens("swerve_left_fast")
    assert {token: float(rows[token][-1]) for token in entry[:2]} == {
        t: official[t]["score"] for t in entry[:2]
    }


def _text(output: str) -> str:
    return " ".join(output.split())


def _scene_pickle(root: Path) -> tuple[Path, dict[str, Any]]:
    """Write the 5-frame roll-out of group 0's pair 0; return its path and content (to break and rewrite)."""
    _, previous, pairs = MAPPING[0]
    content = synthetic_pickle([_raw(pairs[0][1]), _raw(pairs[0][0])], previous, EgoFrameStats())
    path = root / "synthetic" / f"{pairs[0][1]}.pkl"
    write_pickle(path, content)
    return path, content


def _maps(root: Path) -> Path:
    raw = _raw(MAPPING[0][0])
    write_gpkg(
        root / "maps" / raw["map_name"] / "1.0" / "map.gpkg",
        map_tables(raw["map"]),
        storage_epsg=UTM,
        projected=f"epsg:{UTM}",
    )
    return root / "maps"


def _broken(content: dict[str, Any], change: str) -> dict[str, Any]:
    content = copy.deepcopy(content)
    if change == "annotations":
        del content["frames"][4]["annotations"]["track_tokens"]
    elif change == "class":
        content["frames"][4]["annotations"]["names"][0] = "animal"
    elif change == "pose":
        content["frames"][2]["ego_status"]["ego_pose"] = np.array([1.0, np.nan, 0.0])
    elif change == "future":
        content["extended_detections_tracks"] = content["extended_detections_tracks"][:3]
    elif change == "object":
        del content["extended_detections_tracks"][5].tracked_objects.tracked_objects[0].__dict__["_box"]
    return content


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("annotations", "frames[4] (token {now2}).annotations.track_tokens: missing"),
        ("class", "frames[4] (token {now2}).annotations.names: unknown class(es) ['animal']"),
        ("pose", "frames[2] (token {frame2}).ego_status.ego_pose: non-finite value"),
        (
            "future",
            "frames[3] (token {prev2}): 4 future frame(s) (frames after it and extended_detections_tracks); the observation needs 8",
        ),
        ("object", "extended_detections_tracks[5].tracked_objects[0]._box: missing"),
    ],
)
def test_a_malformed_pickle_is_named_and_leaves_nothing(tmp_path: Path, change: str, message: str) -> None:
    path, content = _scene_pickle(tmp_path)
    write_pickle(path, _broken(content, change))
    settings = ImportSettings(_maps(tmp_path), tmp_path / "split")
    outcomes, failed = import_synthetic(tmp_path / "synthetic", settings, None)
    now2 = MAPPING[0][2][0][0]
    expected = message.format(now2=now2, prev2=MAPPING[0][2][0][1], frame2=content["frames"][2]["token"])
    assert [entry["log"] for entry in failed] == [path.name]
    assert failed[0]["reason"].startswith(f"{path}: {expected}"), failed
    assert outcomes == []
    assert not (tmp_path / "split" / "scenes").exists()  # the good scene of the pair is not written either


def test_only_data_is_unpickled(tmp_path: Path) -> None:
    class Payload:
        def __reduce__(self) -> tuple[Any, ...]:
            return (print, ("executed",))

    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"scene_metadata": Payload()}))
    with pytest.raises(
        ScenePickleError,
        match=r"evil.pkl: not a readable synthetic scene pickle \(global builtins.print is not allowed",
    ):
        load_scene_pickle(path)
    private_test = tmp_path / "private.pkl"
    private_test.write_bytes(pickle.dumps([{"token": "x"}] * 5))
    with pytest.raises(SyntheticSceneError, match="a list of frames is the private-test agent input"):
        synthetic_scenes(private_test, load_scene_pickle(private_test), lambda location: None)


def test_a_split_with_a_scene_missing_gets_no_mapping(tmp_path: Path) -> None:
    config = write_group(tmp_path, MAPPING[0], EgoFrameStats())
    missing = MAPPING[0][2][3][0]
    (tmp_path / "synthetic" / f"{missing}.pkl").unlink()
    report = import_two_stage(
        tmp_path / "logs",
        tmp_path / "synthetic",
        config,
        ImportSettings(tmp_path / "maps", tmp_path / "split"),
    )
    assert report["two_stage"]["written"] is False and report["two_stage"]["missing_tokens"] == [missing]
    assert [entry["token"] for entry in report["skipped"]] == [missing]
    assert not (tmp_path / "split" / MAPPING_FILE).exists()
    assert len(list((tmp_path / "split" / "scenes").iterdir())) == 11


def test_stage_mappings_are_read_from_navsim_configs(tmp_path: Path) -> None:
    private = tmp_path / "private_test_hard_two_stage.yaml"
    private.write_text("defaults:\n- scene_filter: private_test_hard_two_stage\nreactive_all_mapping: null\n")
    assert read_stage_mapping(private).groups is None
    broken = tmp_path / "navhard_two_stage.yaml"
    broken.write_text(
        yaml.safe_dump({"reactive_all_mapping": [["0123456789abcdef", "0123456789abcdee", [["x", "y"]]]]})
    )
    with pytest.raises(
        TwoStageSplitError, match=r"reactive_all_mapping\[0\]\[2\]\[0\]\[0\]: token x is not synthetic"
    ):
        read_stage_mapping(broken)
    (tmp_path / "other.yaml").write_text("data_split: test\n")
    with pytest.raises(TwoStageSplitError, match="no reactive_all_mapping"):
        read_stage_mapping(tmp_path / "other.yaml")


# Pickled by nuplan-devkit e924167's own classes (NAVSIM v2.2's pin): one future frame's DetectionsTracks (a
# vehicle, a pedestrian and a traffic cone, given in that reverse order and sorted by TrackedObjects, whose
# cached type ranges were filled) and TrafficLightStatuses (red, yellow, green).
NUPLAN_FUTURE = Path(__file__).parent / "fixtures" / "nuplan-extended-future.pkl"


def test_nuplan_objects_pickled_by_nuplan_itself_are_read(tmp_path: Path) -> None:
    path, _ = _scene_pickle(tmp_path)
    content = load_scene_pickle(path)
    future = load_scene_pickle(NUPLAN_FUTURE)
    for key in ("extended_detections_tracks", "extended_traffic_light_data"):
        content[key] = future[key] * 10
    maps = _maps(tmp_path)
    [prev2, now2] = synthetic_scenes(path, content, lambda location: map_tables_of(maps, location))
    frame = now2.scene["frames"][4]
    assert frame["token"] == f"{now2.token}+1"
    assert frame["timestamp_us"] == now2.scene["frames"][3]["timestamp_us"] + 500_000
    assert frame["objects"] == [
        {
            "track": "car",
            "category": "vehicle",
            "box": [664010.25, 3997001.5, 0.0, 4.6, 1.9, 1.7, -3.0],
            "velocity": [-8.5, 0.75],
        },
        {
            "track": "walker",
            "category": "pedestrian",
            "box": [664020.0, 3997008.0, 0.0, 0.5, 0.6, 1.8, 1.5],
            "velocity": [0.1, 1.2],
        },
        {
            "track": "cone",
            "category": "traffic_cone",
            "box": [664030.0, 3996999.0, 0.0, 0.3, 0.3, 0.7, 0.25],
            "velocity": [0.0, 0.0],
        },
    ]
    assert frame["traffic_lights"] == [["4001", True], ["4002", False], ["4003", False]]
    # prev2's first future frame is now2's current frame; its extended future starts one frame later.
    assert prev2.scene["frames"][4] == now2.scene["frames"][3]
    assert prev2.scene["frames"][5]["objects"] == frame["objects"]


def test_the_import_resumes_without_redoing_scenes(imported) -> None:
    splits, _ = imported
    group = splits[0].parent
    before = {path.name: path.stat().st_mtime_ns for path in (splits[0] / "scenes").iterdir()}
    lost = MAPPING[0][2][2][1]
    (splits[0] / "scenes" / f"{lost}.json.gz").unlink()
    settings = ImportSettings(group / "maps", splits[0])
    report = import_two_stage(group / "logs", group / "synthetic", group / "navhard_two_stage.yaml", settings)
    assert report["this_run"] == {"written": 1, "present": 11, "skipped": 0}
    after = {path.name: path.stat().st_mtime_ns for path in (splits[0] / "scenes").iterdir()}
    assert {name for name in before if after[name] != before[name]} == {f"{lost}.json.gz"}


# The whole reference (40 groups, 480 tokens), where it sits beside the repository -----------------------------

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "epdms-two-stage"
FULL_FAMILIES = sorted(path.stem for path in (REFERENCE / "submissions").glob("*.pkl"))


@pytest.fixture(scope="module")
def whole_reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Return the 40 groups imported from NAVSIM's forms (each from its own map) joined in one split, and its
    cache directory."""
    from scorer.two_stage.split import read_two_stage_split

    root = tmp_path_factory.mktemp("whole")
    split = root / "split"
    (split / "scenes").mkdir(parents=True)
    for index, group in enumerate(read_two_stage_split(REFERENCE / MAPPING_FILE).groups or ()):
        entry = [group.original, group.previous, [list(pair) for pair in group.pairs]]
        group_root = root / f"group{index:02d}"
        config = write_group(group_root, entry, EgoFrameStats(), REFERENCE / "scenes")
        settings = ImportSettings(group_root / "maps", group_root / "split", future_frames=8)
        report = import_two_stage(group_root / "logs", group_root / "synthetic", config, settings)
        assert report["skipped"] == [] and report["two_stage"]["written"], (entry[0], report["skipped"])
        for path in (group_root / "split" / "scenes").iterdir():
            (split / "scenes" / path.name).symlink_to(path)
    (split / MAPPING_FILE).write_bytes((REFERENCE / MAPPING_FILE).read_bytes())
    cache_dir = root / "cache"
    assert build_split_cache(split, cache_dir, [VERSION], workers=2) == {}
    return split, cache_dir


@pytest.mark.full_reference
@pytest.mark.skipif(not REFERENCE.is_dir(), reason="the two-stage reference is not beside the repository")
@pytest.mark.parametrize("family", FULL_FAMILIES)
def test_the_whole_reference_imported_scores_as_the_official_script(whole_reference, family: str) -> None:
    from scorer.submission import load_two_stage_submission

    split, cache_dir = whole_reference
    submission = load_two_stage_submission((REFERENCE / "submissions" / f"{family}.pkl").read_bytes())
    [result] = score_two_stage(split, cache_dir, submission, VERSION, workers=2)
    with gzip.open(REFERENCE / "expected" / f"{family}.two_stage.jsonl.gz", "rt") as handle:
        lines = {line["token"]: line for line in map(json.loads, handle)}
    summary = json.loads((REFERENCE / "expected" / f"{family}.summary.json").read_text())
    assert len(result.rows) == len(lines) == 480 and len(result.groups) == 40
    assert token_mismatches(result, lines) == []
    assert group_mismatches(result, summary["groups"]) == []
    assert same_number(result.combined["score"], summary["summary_rows_exact"]["combined"]["score"])
