"""The whole two-stage reference against the official results, where the reference sits beside the repository
(`../shared/reference/epdms-two-stage`, the project's reference vectors; skipped elsewhere): all 40 groups,
480 tokens, 13 families, each family's NAVSIM pickle (the file the official script read) scored from scenes by
the engine, reactive traffic and all, in 2 processes. Every token's columns, weight and two-frame comfort,
every group, the three summary rows and the official CSV byte for byte; and one family through
`navsim-lb score`. Bit for bit under the official results' OpenBLAS kernels; under others (a host without
AVX-512) progress and the scores within 1e-9 (devkit_kernels.CONTINUOUS_TOLERANCE). Several minutes (the reactive scoring is about 0.15 s per token).
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path
from typing import Any

import pytest
from devkit_kernels import same_number
from two_stage_reference import csv_mismatches, group_mismatches, token_mismatches
from typer.testing import CliRunner

from navsim_lb.cli import app
from scorer.submission import load_two_stage_submission
from scorer.two_stage.aggregate import SCORE_COLUMNS
from scorer.two_stage.result_csv import two_stage_csv
from scorer.two_stage.score import score_two_stage
from scorer.versions import VersionName

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "epdms-two-stage"
FAMILIES = sorted(path.stem for path in (REFERENCE / "submissions").glob("*.pkl"))
WORKERS = 2
VERSION = VersionName.V2_2_TWO_STAGE

pytestmark = [
    pytest.mark.full_reference,
    pytest.mark.skipif(not REFERENCE.is_dir(), reason="the two-stage reference is not beside the repository"),
]


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("cache")


def _official(family: str) -> tuple[dict[str, dict[str, Any]], dict[str, Any]]:
    with gzip.open(REFERENCE / "expected" / f"{family}.two_stage.jsonl.gz", "rt") as handle:
        lines = {line["token"]: line for line in map(json.loads, handle)}
    return lines, json.loads((REFERENCE / "expected" / f"{family}.summary.json").read_text())


@pytest.mark.parametrize("family", FAMILIES)
def test_the_whole_family_is_the_official_one(cache_dir: Path, family: str) -> None:
    submission = load_two_stage_submission((REFERENCE / "submissions" / f"{family}.pkl").read_bytes())
    [result] = score_two_stage(REFERENCE, cache_dir, submission, VERSION, workers=WORKERS)
    lines, summary = _official(family)
    assert len(result.rows) == len(lines) == 480 and len(result.groups) == 40
    assert token_mismatches(result, lines) == []
    assert group_mismatches(result, summary["groups"]) == []
    for name in ("stage_one", "stage_two", "combined"):
        exact = summary["summary_rows_exact"][name]
        assert all(same_number(getattr(result, name)[column], exact[column]) for column in SCORE_COLUMNS), (
            name
        )
    assert result.official and result.notes == ()
    assert csv_mismatches(two_stage_csv(result), (REFERENCE / "expected" / f"{family}.csv").read_text()) == []


def test_the_command_line_writes_the_official_csv(cache_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "results.csv"
    arguments = [
        "score",
        str(REFERENCE),
        str(REFERENCE / "submissions" / "human.json"),
        *("--version", VERSION, "--out", str(out), "--cache-dir", str(cache_dir), "--workers", str(WORKERS)),
    ]
    result = CliRunner().invoke(app, arguments)
    assert result.exit_code == 0, result.output
    official = (REFERENCE / "expected" / "human.csv").read_bytes()
    assert csv_mismatches(out.read_bytes().decode(), official.decode()) == []
