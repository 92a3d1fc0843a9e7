"""`navsim-lb curate` keeps what both baselines allow and prints Table 3."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer
from openscene_builders import write_maps, write_road_log
from typer.testing import CliRunner

from navsim_lb.openscene_cli import register
from scorer.openscene.curation import REPORT_NAME, TABLE_COLUMNS, curate_split, curation_table
from scorer.openscene.importer import ImportSettings, import_logs
from scorer.scene import scene_paths


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("curation")
    write_maps(root / "maps")
    write_road_log(root / "logs")
    import_logs(root / "logs", ImportSettings(root / "maps", root / "split"))
    return root / "split"


def test_curation_keeps_exactly_what_both_agents_allow(split: Path, tmp_path: Path) -> None:
    out = tmp_path / "curated"
    result = curate_split(split, out, tmp_path / "cache")
    tokens = list(scene_paths(split))
    velocity = {r.token: r for r in result.results["constant-velocity"]}
    human = {r.token: r for r in result.results["human"]}
    expected = [
        t
        for t in tokens
        if velocity[t].valid
        and human[t].valid
        and velocity[t].metrics["score"] <= 0.8
        and human[t].metrics["score"] >= 0.8
    ]
    assert result.kept == tuple(expected)
    assert set(result.dropped) == set(tokens) - set(expected)
    for token, reason in result.dropped.items():
        if velocity[token].metrics["score"] > 0.8:
            assert reason.startswith("near-trivial")
        else:
            assert reason.startswith("likely annotation error")
    originals = scene_paths(split)
    assert {t: p.read_bytes() for t, p in scene_paths(out).items()} == {
        t: originals[t].read_bytes() for t in expected
    }
    report = json.loads((out / REPORT_NAME).read_text())
    assert report["kept"] == expected and report["table"] == curation_table(result)


def test_table_3_rows_are_percent_means_over_all_and_kept_scenes(split: Path, tmp_path: Path) -> None:
    result = curate_split(split, tmp_path / "curated", tmp_path / "cache")
    rows = curation_table(result)
    assert rows[0] == ["Agent", "Scenes", "Tokens", "NC", "DAC", "TTC", "C", "EP", "PDMS"]
    assert [row[:2] for row in rows[1:]] == [
        ["Constant velocity", "all"],
        ["Constant velocity", "curated"],
        ["Human", "all"],
        ["Human", "curated"],
    ]
    all_human = result.results["human"]
    expected = [f"{100 * np.mean([r.metrics[column] for r in all_human]):.1f}" for _, column in TABLE_COLUMNS]
    assert rows[3][2:] == [str(len(all_human)), *expected]
    assert rows[2][2] == rows[4][2] == str(len(result.kept))


def test_a_threshold_above_any_score_drops_every_scene(split: Path, tmp_path: Path) -> None:
    result = curate_split(split, tmp_path / "curated", tmp_path / "cache", threshold=1.5)
    assert result.kept == () and all(r.startswith("likely annotation error") for r in result.dropped.values())


def test_curation_refuses_to_overwrite(split: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="must be written to another directory"):
        curate_split(split, split, tmp_path / "cache")
    (tmp_path / "out" / "scenes").mkdir(parents=True)
    (tmp_path / "out" / "scenes" / "x.json").write_text("{}")
    with pytest.raises(ValueError, match="already holds scenes"):
        curate_split(split, tmp_path / "out", tmp_path / "cache")


def test_cli_curate_prints_the_table(split: Path, tmp_path: Path) -> None:
    app = typer.Typer()
    register(app)
    result = CliRunner().invoke(
        app,
        ["curate", str(split), "--out", str(tmp_path / "curated"), "--cache-dir", str(tmp_path / "cache")],
        env={"COLUMNS": "200"},  # one table row per line
    )
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "Constant velocity" in text and "Human" in text and "of 26 scenes" in text
