"""The engine's command line end to end: synth, baseline, cache, score (CSV and summary), and its errors."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from rich.console import Console
from typer.testing import CliRunner

from navsim_lb.cli import app
from navsim_lb.report import summary_rows, summary_table
from navsim_lb.terminal import TextTable, plain_table, rich_table
from scorer.evaluate import TokenResult, score_tokens
from scorer.submission import load_submission
from scorer.versions import METRIC_LABELS, VERSIONS

runner = CliRunner()


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "split"
    result = runner.invoke(app, ["synth", str(out), "--scenes", "6", "--seed", "4"])
    assert result.exit_code == 0, result.output
    return out


def test_synth_refuses_a_used_directory(split: Path) -> None:
    result = runner.invoke(app, ["synth", str(split), "--scenes", "2"])
    assert result.exit_code == 2 and "choose an empty directory" in result.output


def test_baseline_cache_and_score_write_the_devkit_csv(split: Path, tmp_path: Path) -> None:
    submission = tmp_path / "human.json"
    assert runner.invoke(app, ["baseline", "human", str(split), "--out", str(submission)]).exit_code == 0
    cache_dir = tmp_path / "cache"
    result = runner.invoke(app, ["cache", str(split), "--cache-dir", str(cache_dir)])
    assert result.exit_code == 0 and "cached 6 of 6 scenes" in result.output
    csv = tmp_path / "results.csv"
    result = runner.invoke(
        app,
        [
            "score",
            str(split),
            str(submission),
            "--version",
            "v1.0",
            "--out",
            str(csv),
            "--cache-dir",
            str(cache_dir),
        ],
    )
    assert result.exit_code == 0, result.output
    table = pd.read_csv(csv, index_col=0)
    assert list(table.columns) == ["token", "valid", *VERSIONS["v1.0"].result_columns, "error"]
    assert table["token"].iloc[-1] == "average" and len(table) == 7
    predictions = load_submission(submission.read_bytes()).seeds[0]
    direct = {r.token: r.metrics["score"] for r in score_tokens(split, cache_dir, predictions, "v1.0")}
    scores = dict(zip(table["token"].iloc[:-1], table["score"].iloc[:-1], strict=True))
    assert scores == pytest.approx(direct, abs=0, rel=1e-15)
    assert table["score"].iloc[-1] == pytest.approx(np.mean(list(direct.values())), rel=1e-12)


def test_score_explains_a_broken_submission(split: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken.json"
    broken.write_text(
        json.dumps({"format": "navsim-lb/submission", "version": 1, "predictions": {"x": [[0, 0]]}})
    )
    result = runner.invoke(app, ["score", str(split), str(broken), "--cache-dir", str(tmp_path / "c")])
    assert result.exit_code == 2
    # The message wraps at 80 columns wherever the path's length puts it.
    assert "expected 8 poses of [x, y, heading], got shape (1, 2)" in " ".join(result.output.split())
    result = runner.invoke(app, ["score", str(split), str(broken), "--version", "v9"])
    assert result.exit_code == 2 and "'v9' is not one of 'v1.0', 'v1.1'" in " ".join(
        line.strip("│ ") for line in result.output.splitlines()
    )


def test_score_prints_a_method_name_as_written(split: Path, tmp_path: Path) -> None:
    """A method name is the team's text: markup or emoji codes in it are printed literally, never rendered
    (an unmatched closing tag crashed the summary)."""
    submission = tmp_path / "cv.json"
    assert (
        runner.invoke(app, ["baseline", "constant-velocity", str(split), "--out", str(submission)]).exit_code
        == 0
    )
    document = json.loads(submission.read_text())
    document["method"] = "[/bold] :thumbs_up: [red]x"
    submission.write_text(json.dumps(document))
    result = runner.invoke(app, ["score", str(split), str(submission), "--cache-dir", str(tmp_path / "c")])
    assert result.exit_code == 0, result.output
    assert "[/bold] :thumbs_up: [red]x on split" in result.output


def test_multi_seed_summary_has_per_seed_rows_and_mean_std_max() -> None:
    def rows(seed: int, score: float, valid: bool = True) -> list[TokenResult]:
        metrics = dict.fromkeys(VERSIONS["v1.1"].result_columns, score)
        return [
            TokenResult("a", seed, True, metrics),
            TokenResult("b", seed, valid, metrics if valid else {}, None if valid else "broken"),
        ]

    table = summary_rows(rows(0, 0.5) + rows(1, 0.9, valid=False), VERSIONS["v1.1"])
    header, *body = table
    score = header.index("PDMS")
    assert [row[0] for row in body] == ["0", "1", "mean", "std", "max"]
    # Seed 1 has an unscored token: it counts 0 in the mean and is reported. Scores in %, as on the board.
    assert body[1][score] == "45.0" and body[1][header.index("unscored")] == "1"
    assert body[2][score] == "47.5" and body[3][score] == "2.5" and body[4][score] == "50.0"


def _drawn(table: TextTable) -> str:
    """Return `table` as rich draws it on an 80-column terminal (trailing spaces off), after checking that the
    plain text printed in a log or a pipe reads the same."""
    console = Console(width=80, record=True, file=io.StringIO(), emoji=False)
    console.print(rich_table(table))
    text = "\n".join(line.rstrip() for line in console.export_text().splitlines())
    assert plain_table(table) == text
    return text


@pytest.mark.parametrize("value", [0.987654, 1.0])  # "100.0" everywhere is the widest table
@pytest.mark.parametrize("version", list(VERSIONS))
def test_summary_table_reads_in_80_columns(version: str, value: float) -> None:
    results = [
        TokenResult(f"token{index}", seed, True, dict.fromkeys(VERSIONS[version].result_columns, value))
        for seed in range(3)
        for index in range(12000)
    ]
    text = _drawn(summary_table(results, VERSIONS[version], "a method with a long name on private_test_e2e"))
    lines = text.splitlines()
    assert max(len(line) for line in lines) <= 80 and "…" not in text
    header = next(line.split() for line in lines if line.split()[:1] == ["seed"])
    columns = VERSIONS[version].result_columns
    labels = [METRIC_LABELS[column] for column in columns[:-1]]
    assert header == ["seed", *labels, VERSIONS[version].score_label, "tokens", "unscored"]
    assert next(line.split() for line in lines if line.split()[:1] == ["mean"])[1:] == [
        f"{100 * value:.1f}"
    ] * len(columns)
    assert f"DDC: {VERSIONS[version].ddc_role}" in " ".join(text.split())


@pytest.mark.parametrize("version", ["v2.2", "v2.2-prefix"])
def test_score_under_v2_2_writes_the_official_one_stage_layout(version: str, tmp_path: Path) -> None:
    """`navsim-lb score --version v2.2` (or v2.2-prefix): token, valid, the nine columns and the score, EC empty
    where no adjacent frame was scored, and the `average_all_frames` row skipping it (the official average)."""
    split = Path(__file__).parent / "fixtures" / "epdms" / "probes"
    out = tmp_path / f"{version}.csv"
    result = CliRunner().invoke(
        app,
        [
            "score",
            str(split),
            str(split / "submissions" / "cv_straight.json"),
            "--version",
            version,
            "--out",
            str(out),
            "--cache-dir",
            str(tmp_path / "cache"),
        ],
    )
    assert result.exit_code == 0, result.output
    table = pd.read_csv(out, index_col=0)
    assert list(table.columns) == ["token", "valid", *VERSIONS[version].result_columns, "error"]
    assert table["token"].iloc[-1] == "average_all_frames"
    rows = table.iloc[:-1]
    undefined = rows["two_frame_extended_comfort"].isna()
    assert 0 < undefined.sum() < len(rows)
    assert table["two_frame_extended_comfort"].iloc[-1] == rows["two_frame_extended_comfort"].mean()
    assert f"EPDMS {version}" in result.output
