"""Two-stage EPDMS scored end to end from scenes (v2.2-two-stage): the first 3 groups of the reference
(fixtures/epdms-two-stage-reactive, a two-stage split of 36 scenes) against the official values of every
family (fixtures/epdms-two-stage): each token's columns, two-frame comfort (partner and RMS), weight and score,
and each group's four averages and value, bit for bit. Then `navsim-lb score` on the cases where the official
script crashes: the affected group scored with what is defined and the reason said, never the whole run."""

from __future__ import annotations

import gzip
import json
import math
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
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
from scorer.submission import SubmissionMetadata, TwoStageSubmission, load_two_stage_submission
from scorer.two_stage.score import score_two_stage
from scorer.versions import VersionName

FIXTURES = Path(__file__).parent / "fixtures" / "epdms-two-stage-reactive"
ONE_STAGE_SPLIT = Path(__file__).parent / "fixtures" / "reference"
VERSION = VersionName.V2_2_TWO_STAGE
MAPPING: list[Any] = json.loads((FIXTURES / "two_stage.json").read_text())["reactive_all_mapping"]
runner = CliRunner()


@cache
def _predictions(family: str) -> dict[str, list[list[float]]]:
    with gzip.open(FIXTURES / "predictions.json.gz", "rt") as handle:
        predictions: dict[str, dict[str, list[list[float]]]] = json.load(handle)
    return predictions[family]


def _stage_tokens(mapping: list[Any]) -> tuple[list[str], list[str]]:
    first = [token for original, previous, _ in mapping for token in (original, previous)]
    second = [token for _, _, pairs in mapping for pair in pairs for token in pair]
    return first, second


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("cache")
    assert build_split_cache(FIXTURES, directory, [VERSION]) == {}
    return directory


@pytest.mark.parametrize("family", FAMILIES)
def test_tokens_and_groups_are_the_official_ones(cache_dir: Path, family: str) -> None:
    first, second = _stage_tokens(MAPPING)
    poses = {token: np.array(value) for token, value in _predictions(family).items()}
    submission = TwoStageSubmission(
        SubmissionMetadata(), ({t: poses[t] for t in first},), ({t: poses[t] for t in second},)
    )
    [result] = score_two_stage(FIXTURES, cache_dir, submission, VERSION)
    assert [row.token for row in result.rows] == first + second
    assert token_mismatches(result, official_tokens(family)) == []
    assert len(result.groups) == 3
    assert group_mismatches(result, official_summary(family)["groups"]) == []
    assert result.official and result.notes == ()


# The cases where the official script crashes, through the command line --------------------------------


def _split(root: Path, mapping: list[Any] | None, broken: str | None = None) -> Path:
    """Return a two-stage split of every fixture scene (`broken`'s file damaged) with `mapping`."""
    split = root / "split"
    (split / "scenes").mkdir(parents=True)
    for path in (FIXTURES / "scenes").iterdir():
        if path.name.startswith(f"{broken}."):
            (split / "scenes" / path.name).write_bytes(b"\x1f\x8b not a scene")
        else:
            (split / "scenes" / path.name).symlink_to(path)
    document = {"format": "navsim-lb/two-stage-split", "version": 1, "reactive_all_mapping": mapping}
    (split / "two_stage.json").write_text(json.dumps(document))
    return split


def _submission(root: Path, first: list[str], second: list[str], seeds: int = 1) -> Path:
    predictions = _predictions("human")
    document = {
        "format": "navsim-lb/submission-two-stage",
        "version": 1,
        "method": "human",
        "first_stage_predictions": [{token: predictions[token] for token in first}] * seeds,
        "second_stage_predictions": [{token: predictions[token] for token in second}] * seeds,
    }
    path = root / "submission.json"
    path.write_text(json.dumps(document))
    return path


def _score(split: Path, submission: Path, cache_dir: Path, *options: str) -> tuple[str, list[list[str]]]:
    """Run `navsim-lb score`; return its output (lines unwrapped) and the CSV's rows."""
    out = split.parent / "results.csv"
    arguments = ["score", str(split), str(submission), "--version", VERSION, "--out", str(out)]
    result = runner.invoke(app, [*arguments, "--cache-dir", str(cache_dir), *options])
    assert result.exit_code == 0, result.output
    rows = [line.split(",") for line in out.read_text().splitlines()] if out.exists() else []
    return " ".join(result.output.split()), rows


def load_submission(path: Path) -> TwoStageSubmission:
    return load_two_stage_submission(path.read_bytes())


def _official_group(index: int) -> float:
    value: float = official_summary("human")["groups"][index]["combined"]
    return value


def test_a_failed_token_counts_zero_in_its_group_and_the_run_goes_on(tmp_path: Path, cache_dir: Path) -> None:
    failed = MAPPING[0][2][1][0]  # a now2 token whose scene cannot be read
    split = _split(tmp_path, MAPPING[:2], broken=failed)
    first, second = _stage_tokens(MAPPING[:2])
    text, rows = _score(split, _submission(tmp_path, first, second), cache_dir)
    assert f"warning: token {failed} failed: it counts 0 in its group" in text
    assert [row[1:3] for row in rows if row[1] == failed] == [[failed, "False"]]
    assert rows[-1][1:3] == ["extended_pdm_score_combined", "False"]  # not what the official script gives
    [result] = score_two_stage(split, cache_dir, load_submission(tmp_path / "submission.json"), VERSION)
    assert result.groups[0].detail["failed"] == [failed]
    assert result.groups[1].combined["score"] == _official_group(1)
    assert result.groups[0].combined["score"] != _official_group(0)
    assert not math.isnan(result.score)


def test_tokens_no_group_covers_are_scored_and_left_out_of_the_means(tmp_path: Path, cache_dir: Path) -> None:
    split = _split(tmp_path, MAPPING[:1])
    first, second = _stage_tokens(MAPPING[:2])  # the second group's tokens are in no group of this split
    text, rows = _score(split, _submission(tmp_path, first, second), cache_dir)
    assert f"first_stage_predictions, token {MAPPING[1][0]}: token is not in the split" in text
    assert f"token {MAPPING[1][0]} is in no group of the mapping" in text
    assert len(rows) == 1 + 24 + 3 and all(row[2] == "True" for row in rows[1:25])
    assert float(rows[-1][-1]) == _official_group(0)


def test_a_group_token_not_submitted_counts_zero(tmp_path: Path, cache_dir: Path) -> None:
    split = _split(tmp_path, MAPPING[:1])
    first, second = _stage_tokens(MAPPING[:1])
    missing = MAPPING[0][2][3][1]
    text, rows = _score(split, _submission(tmp_path, first, [t for t in second if t != missing]), cache_dir)
    assert f"second_stage_predictions, token {missing}: token of the split is missing" in text
    assert f"token {missing} of a scored group was not submitted: it counts 0" in text
    assert len(rows) == 1 + 11 + 3 and rows[-1][2] == "False"
    [result] = score_two_stage(split, cache_dir, load_submission(tmp_path / "submission.json"), VERSION)
    partner = MAPPING[0][2][3][0]  # its now2: no EC without it
    assert result.groups[0].detail == {
        "not_submitted": [missing],
        "comfort_undefined": [partner],
        "uniform_weights": ["previous"],
    }
    row = next(row for row in result.rows if row.token == partner)
    assert row.detail["two_frame_extended_comfort"] == {
        "previous_token": missing,
        "undefined": f"its partner {missing} was not scored",
    }


def test_equal_start_times_leave_two_frame_comfort_undefined_with_the_reason(
    tmp_path: Path, cache_dir: Path
) -> None:
    """Pairs of two now2 (and two prev2) tokens: both start 4 s (3.5 s) after orig, the official EC asserts."""
    original, previous, pairs = MAPPING[0]
    (now_a, previous_a), (now_b, previous_b), *rest = pairs
    mapping = [[original, previous, [[now_a, now_b], [previous_a, previous_b], *rest]], MAPPING[1]]
    split = _split(tmp_path, mapping)
    first, second = _stage_tokens(mapping)
    text, rows = _score(split, _submission(tmp_path, first, second), cache_dir)
    assert f"token {now_a}: two-frame extended comfort undefined, left out of the means" in text
    column = rows[0].index("two_frame_extended_comfort_stage_two")
    assert [row[column] for row in rows if row[1] in (now_a, now_b)] == ["", ""]
    [result] = score_two_stage(split, cache_dir, load_submission(tmp_path / "submission.json"), VERSION)
    row = next(row for row in result.rows if row.token == now_b)
    assert math.isnan(row.metrics["two_frame_extended_comfort"])
    assert row.detail["two_frame_extended_comfort"] == {
        "current_token": now_a,
        "undefined": "the official code pairs this frame and then fails: frames 0.0 s apart: the devkit "
        "asserts 0 < Δt < 0.55",
    }
    assert result.groups[0].detail == {"comfort_undefined": [now_a, now_b, previous_a, previous_b]}
    assert result.groups[1].combined["score"] == _official_group(1)


def test_a_null_mapping_scores_every_token_and_leaves_the_summary_undefined(
    tmp_path: Path, cache_dir: Path
) -> None:
    split = _split(tmp_path, None)
    first, second = _stage_tokens(MAPPING)
    text, _ = _score(split, _submission(tmp_path, first, second, seeds=2), cache_dir)
    assert "the split has no stage mapping (reactive_all_mapping is null)" in text
    seed_rows = [[line.split(",") for line in path.read_text().splitlines()] for path in _seed_csvs(split)]
    for rows in seed_rows:
        assert len(rows) == 1 + 36 + 3 and all(row[2] == "True" for row in rows[1:37])
        assert rows[-1] == ["38", "extended_pdm_score_combined", "False", *[""] * 19]
    assert "0 – – – 0 0 no" in text and "mean – – –" in text


def _seed_csvs(split: Path) -> list[Path]:
    return [split.parent / f"results.seed{index}.csv" for index in range(2)]


def test_several_seeds_write_one_official_csv_each(tmp_path: Path, cache_dir: Path) -> None:
    split = _split(tmp_path, MAPPING[:1])
    first, second = _stage_tokens(MAPPING[:1])
    text, _ = _score(split, _submission(tmp_path, first, second, seeds=2), cache_dir, "--workers", "2")
    one, two = (path.read_text() for path in _seed_csvs(split))
    assert one == two and float(one.splitlines()[-1].split(",")[-1]) == _official_group(0)
    # A long temporary path may wrap anywhere in the console's width: compared without white space.
    assert f"wrote{split.parent / 'results.seed1.csv'}" in "".join(text.split())
    assert "mean" in text and "std" in text and "max" in text


def test_versions_and_splits_of_the_other_kind_are_refused(tmp_path: Path, cache_dir: Path) -> None:
    first, second = _stage_tokens(MAPPING[:1])
    submission = _submission(tmp_path, first, second)
    arguments = ["score", str(ONE_STAGE_SPLIT), str(submission), "--cache-dir", str(cache_dir)]
    result = runner.invoke(app, [*arguments, "--version", VERSION])
    assert result.exit_code == 2
    assert "no two_stage.json, so not a two-stage split" in " ".join(result.output.split())
    result = runner.invoke(app, ["score", str(FIXTURES), str(submission), "--version", "v2.2"])
    assert result.exit_code == 2
    assert "scored under different metric versions" in " ".join(result.output.split())
    one_stage = ONE_STAGE_SPLIT / "submissions" / "human.json"
    result = runner.invoke(app, ["score", str(FIXTURES), str(one_stage), "--version", VERSION])
    assert result.exit_code == 2 and "first_stage_predictions" in result.output
    result = runner.invoke(app, [*arguments, "--version", "v2.2", "--workers", "2"])
    assert result.exit_code == 2
    assert "several are for the two-stage versions" in " ".join(result.output.split())
