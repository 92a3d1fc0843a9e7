"""The whole engine (our own cache, PDM-Closed included) against the official devkit's per-token results.

Every column must be equal, bit for bit, under the official results' OpenBLAS kernels (`scorer.blas`
selects them where the CPU can run them). Under other kernels `pinv` rounds differently in the tracker's
fits, and ego progress and the score may differ in the last bits (up to 3e-13 seen, at most
CONTINUOUS_TOLERANCE); multipliers and discrete scores must still be equal.
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import pytest
from devkit_kernels import CONTINUOUS_TOLERANCE, V1_VERSIONS

from scorer.evaluate import TokenResult, build_split_cache, score_tokens
from scorer.submission import load_submission
from scorer.versions import METRIC_COLUMNS, VERSIONS

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
CONTINUOUS_COLUMNS = {"ego_progress", "score"}
FAMILIES = sorted(path.stem for path in (REFERENCE / "submissions").glob("*.json"))


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("cache")
    assert build_split_cache(REFERENCE, directory, list(VERSIONS)) == {}
    return directory


def _expected(family: str, version: str) -> dict[str, dict[str, object]]:
    with gzip.open(REFERENCE / "expected" / f"{family}.{version}.jsonl.gz", "rt") as handle:
        return {row["token"]: row for row in map(json.loads, handle)}


def _agrees(column: str, ours: float, devkit: object) -> bool:
    if column in CONTINUOUS_COLUMNS:
        return abs(ours - float(devkit)) <= CONTINUOUS_TOLERANCE  # type: ignore[arg-type]
    return ours == devkit


def _mismatches(results: list[TokenResult], expected: dict[str, dict[str, object]]) -> list[str]:
    found = []
    for result in results:
        row = expected[result.token]
        if not result.valid:
            found.append(f"{result.token}: invalid ({result.error})")
            continue
        found += [
            f"{result.token}: {column} {result.metrics[column]!r} != {row[column]!r}"
            for column in METRIC_COLUMNS
            if not _agrees(column, result.metrics[column], row[column])
        ]
    return found


@pytest.mark.parametrize("version", V1_VERSIONS)
@pytest.mark.parametrize("family", FAMILIES)
def test_family_matches_the_devkit(cache_dir: Path, family: str, version: str) -> None:
    submission = load_submission(
        (REFERENCE / "submissions" / f"{family}.json").read_bytes(), f"{family}.json"
    )
    results = score_tokens(REFERENCE, cache_dir, submission.seeds[0], version)
    assert len(results) == 40
    assert _mismatches(results, _expected(family, version)) == []
