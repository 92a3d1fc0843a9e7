"""The two-stage aggregation gives the official weights, group values and summary rows bit for bit, fed the
official per-token values of the reference excerpt (13 families x 40 groups x 12 tokens)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from two_stage_reference import (
    FAMILIES,
    FIXTURE,
    SPLIT,
    aggregation_input,
    official_summary,
    official_tokens,
)

from scorer.metrics.aggregation import nan_skipping_mean
from scorer.submission import load_two_stage_submission
from scorer.two_stage.aggregate import GROUP_PARTS, SCORE_COLUMNS, aggregate_two_stage
from scorer.two_stage.result_csv import write_two_stage_csv
from scorer.two_stage.sums import sums_by_group
from scorer.two_stage.weights import global_endpoints


def _same(actual: float, expected: float | None) -> bool:
    """Bit equality, NaN (None in JSON) equal to NaN."""
    if expected is None:
        return bool(np.isnan(actual))
    return actual == expected


@pytest.mark.parametrize("family", FAMILIES)
def test_weights_are_the_official_ones(family: str) -> None:
    result = aggregate_two_stage(aggregation_input(family), SPLIT)
    lines = official_tokens(family)
    assert set(result.weight_detail) == set(SPLIT.stage_two_tokens)
    for token, detail in result.weight_detail.items():
        assert detail == lines[token]["weight_detail"], token
    assert result.weights == {token: lines[token]["weight"] for token in lines}


@pytest.mark.parametrize("family", FAMILIES)
def test_groups_and_summary_rows_are_the_official_ones(family: str) -> None:
    result = aggregate_two_stage(aggregation_input(family), SPLIT)
    summary = official_summary(family)
    assert result.official and result.notes == () and summary["pseudo_closed_loop_valid"]
    assert len(result.groups) == len(summary["groups"]) == 40
    for group, expected in zip(result.groups, summary["groups"], strict=True):
        assert (group.original, group.previous) == (expected["original"], expected["previous"])
        # The official detail lists the four weighted averages g1s1, g1s2, g2s1, g2s2.
        for part, columns in zip(GROUP_PARTS, expected["columns"], strict=True):
            assert all(_same(group.parts[part][c], columns[c]) for c in SCORE_COLUMNS), (group.original, part)
        assert group.combined["score"] == expected["combined"]
    for name in ("stage_one", "stage_two", "combined"):
        exact = summary["summary_rows_exact"][name]
        assert all(_same(getattr(result, name)[c], exact[c]) for c in SCORE_COLUMNS), name
    assert result.score == summary["summary_rows_exact"]["combined"]["score"]


def test_endpoints_are_the_submitted_last_poses_made_global() -> None:
    submission = load_two_stage_submission((FIXTURE / "submissions" / "human.json").read_bytes())
    egos = json.loads((FIXTURE / "stage_one_egos.json").read_text())
    tokens = list(submission.first_stage[0])
    endpoints = global_endpoints(
        np.stack([submission.first_stage[0][token] for token in tokens]), np.array([egos[t] for t in tokens])
    )
    lines = official_tokens("human")
    assert endpoints.tolist() == [lines[token]["endpoint"] for token in tokens]


@pytest.mark.parametrize("size", [1, 5, 7, 8, 9, 20, 127, 128, 129, 300])
def test_group_sums_and_means_add_as_numpy_adds_one_array(size: int) -> None:
    rng = np.random.default_rng(size)
    values = rng.normal(size=(3, 700)) * 10.0 ** rng.integers(-6, 6, size=(3, 700))
    members = [rng.permutation(700)[:size] for _ in range(4)] + [np.arange(0)]
    sums = sums_by_group(values, members)
    for group, member in enumerate(members):
        for column in range(3):
            assert sums[column, group] == (values[column, member].copy().sum() if len(member) else 0.0)
    with_nan = np.where(rng.random((3, size)) < 0.2, np.nan, values[:, :size])
    zero_filled = np.where(np.isnan(with_nan), 0.0, with_nan)
    counts = (~np.isnan(with_nan)).sum(axis=1)
    expected = [zero_filled[c].copy().sum() / counts[c] if counts[c] else np.nan for c in range(3)]
    np.testing.assert_array_equal(nan_skipping_mean(with_nan), expected)


@pytest.mark.parametrize("family", FAMILIES)
def test_the_csv_is_the_official_one_byte_for_byte(family: str, tmp_path: Path) -> None:
    result = aggregate_two_stage(aggregation_input(family), SPLIT)
    write_two_stage_csv(result, tmp_path / "result.csv")
    assert (tmp_path / "result.csv").read_bytes() == (FIXTURE / "expected" / f"{family}.csv").read_bytes()


def test_writing_the_csv_imports_no_pandas() -> None:
    code = "import sys, scorer.two_stage.result_csv; sys.exit('pandas' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0
