"""NAVSIM's two-stage data through the OpenScene import, scored against the official results.

The 3 groups of the two-stage fixture (fixtures/epdms-two-stage-reactive) are written as NAVSIM holds them:
the logged frames `orig` and `prev` as one OpenScene log, the map as a GeoPackage, each synthetic pair 0 as a
5-frame roll-out pickle (prev2 = frames[:-1], now2 = frames[1:]) and every other synthetic scene as a 4-frame
`Scene.save_to_disk` pickle with extended tracks and lights, the mapping as NAVSIM's split YAML. Imported
again, every token of every group scores as the official script did, bit for bit (tests/two_stage_reference).
"""

from __future__ import annotations

import gzip
import json
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from openscene_builders import map_tables, write_gpkg, write_log
from synthetic_builders import EgoFrameStats, stage_one_log, synthetic_pickle, write_pickle
from two_stage_reference import (
    FAMILIES,
    group_mismatches,
    official_summary,
    official_tokens,
    token_mismatches,
)

from scorer.evaluate import build_split_cache
from scorer.openscene.importer import ImportSettings, scene_path
from scorer.openscene.two_stage_import import import_two_stage
from scorer.scene import load_scene
from scorer.submission import SubmissionMetadata, TwoStageSubmission
from scorer.two_stage.score import score_two_stage
from scorer.two_stage.split import load_two_stage_split
from scorer.versions import VersionName

FIXTURES = Path(__file__).parent / "fixtures" / "epdms-two-stage-reactive"
MAPPING: list[Any] = json.loads((FIXTURES / "two_stage.json").read_text())["reactive_all_mapping"]
VERSION = VersionName.V2_2_TWO_STAGE
UTM = 32611  # the fixture maps are stored in their projected system


@cache
def _raw(token: str) -> dict[str, Any]:
    return json.loads(gzip.decompress((FIXTURES / "scenes" / f"{token}.json.gz").read_bytes()))


@cache
def _predictions(family: str) -> dict[str, list[list[float]]]:
    with gzip.open(FIXTURES / "predictions.json.gz", "rt") as handle:
        predictions: dict[str, dict[str, list[list[float]]]] = json.load(handle)
    return predictions[family]


def write_group(root: Path, entry: list[Any], stats: EgoFrameStats) -> Path:
    """Write one mapping entry in NAVSIM's forms under `root`; return the split YAML."""
    original, previous, pairs = entry
    raw = _raw(original)
    write_gpkg(
        root / "maps" / raw["map_name"] / "1.0" / "map.gpkg",
        map_tables(raw["map"]),
        storage_epsg=UTM,
        projected=f"epsg:{UTM}",
    )
    write_log(root / "logs" / f"{raw['log_name']}.pkl", stage_one_log(raw, _raw(previous), stats))
    for index, (now2, prev2) in enumerate(pairs):
        if index == 0:  # the private-test form of a roll-out
            content = synthetic_pickle([_raw(prev2), _raw(now2)], previous, stats)
            write_pickle(root / "synthetic" / f"{prev2}.pkl", content)
            continue
        for token, first_stage in ((now2, original), (prev2, previous)):
            write_pickle(
                root / "synthetic" / f"{token}.pkl", synthetic_pickle([_raw(token)], first_stage, stats)
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
