"""Metric-version regression guard: golden per-token results of a fixed synthetic split under every registered
version, and of a fixed synthetic two-stage split with its aggregation under every two-stage version.

The splits are regenerated from their seed each run (the generators are deterministic), scored with every
trajectory family, and compared with the versioned golden files. The two-stage golden
(`<version>.aggregation.jsonl`) holds per family every token's columns, stage and weight, every group's four
parts and value, and the three summary rows (stage one, stage two, combined, with whether the official
script would have given them): what weights, groups and the combined score come to, beside what each token
scores.
"""

from __future__ import annotations

import json
import math
import tempfile
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

from scorer.evaluate import score_tokens
from scorer.regression.families import FAMILIES
from scorer.scene import iter_scenes
from scorer.versions import VERSIONS, get_version

GOLDEN_DIR = Path(__file__).parent / "golden"
SPLIT_SCENES = 24
SPLIT_SEED = 20261122
# The two-stage split: groups of NAVSIM's form (orig, prev and synthetic pairs), small enough to score in
# seconds, with enough pairs that the weights are not all uniform.
TWO_STAGE_GROUPS = 4
TWO_STAGE_PAIRS = 2
AGGREGATION = "aggregation"  # the two-stage golden's name: <version>.aggregation
TOLERANCE = 1e-9

Change = tuple[str, str, str, str, object, object]


def compute_results(
    work_dir: Path, progress: Callable[[str, int], AbstractContextManager[Callable[[int], None]]]
) -> dict[str, list[dict[str, object]]]:
    """Return golden name -> rows (family, token, values): per version, the regression split's rows (valid,
    metrics); per two-stage version, `<version>.aggregation`, the two-stage split's (`two_stage_rows`)."""
    from scorer.synth import synthesize_split

    split = work_dir / "regression_split"
    synthesize_split(split, SPLIT_SCENES, SPLIT_SEED)
    scenes = list(iter_scenes(split))
    rows: dict[str, list[dict[str, object]]] = {version: [] for version in VERSIONS}
    with progress("regression split", len(VERSIONS) * len(FAMILIES) * len(scenes)) as advance:
        for version in VERSIONS:
            for family, make in FAMILIES.items():
                predictions = {scene.token: make(scene) for scene in scenes}
                for result in score_tokens(split, work_dir / "cache", predictions, version, progress=advance):
                    rows[version].append(
                        {"family": family, "token": result.token, "valid": result.valid, **result.metrics}
                    )
    return rows | two_stage_rows(work_dir, progress)


def two_stage_rows(
    work_dir: Path, progress: Callable[[str, int], AbstractContextManager[Callable[[int], None]]]
) -> dict[str, list[dict[str, object]]]:
    """Return `<version>.aggregation` -> rows of the two-stage regression split per family under each two-stage
    version: a row per token (its columns, stage and weight), per group (`group <orig>`: its parts and value,
    as `<part>.<column>`) and per summary row (`SUMMARY_TOKENS`, the combined one with `official`)."""
    from scorer.submission import SubmissionMetadata, TwoStageSubmission
    from scorer.synth.two_stage import synthesize_two_stage_split
    from scorer.two_stage.result_csv import SUMMARY_TOKENS
    from scorer.two_stage.score import score_two_stage
    from scorer.two_stage.split import load_two_stage_split
    from scorer.versions import TWO_STAGE_VERSIONS

    split = work_dir / "two_stage_regression_split"
    synthesize_two_stage_split(split, TWO_STAGE_GROUPS, TWO_STAGE_PAIRS, SPLIT_SEED)
    stages = load_two_stage_split(split)
    scenes = {scene.token: scene for scene in iter_scenes(split)}
    rows: dict[str, list[dict[str, object]]] = {}
    with progress("two-stage regression split", len(TWO_STAGE_VERSIONS) * len(FAMILIES)) as advance:
        for version in TWO_STAGE_VERSIONS:
            found = rows.setdefault(f"{version}.{AGGREGATION}", [])
            for family, make in FAMILIES.items():
                first, second = (
                    {token: make(scenes[token]) for token in tokens}
                    for tokens in (stages.stage_one_tokens, stages.stage_two_tokens)
                )
                submission = TwoStageSubmission(SubmissionMetadata(method=family), (first,), (second,))
                [result] = score_two_stage(split, work_dir / "cache", submission, version)
                found.extend(
                    {
                        "family": family,
                        "token": row.token,
                        "stage": 1 if row.token in first else 2,
                        "weight": result.weights.get(row.token, math.nan),
                        "valid": row.valid,
                        **row.metrics,
                    }
                    for row in result.rows
                )
                found.extend(
                    {
                        "family": family,
                        "token": f"group {group.original}",
                        **{
                            f"{part}.{column}": value
                            for part, values in (*group.parts.items(), ("combined", group.combined))
                            for column, value in values.items()
                        },
                    }
                    for group in result.groups
                )
                summaries = (
                    result.stage_one,
                    result.stage_two,
                    {**result.combined, "official": result.official},
                )
                found.extend(
                    {"family": family, "token": token, **summary}
                    for token, summary in zip(SUMMARY_TOKENS, summaries, strict=True)
                )
                advance(1)
    return rows


def _golden_path(version: str) -> Path:
    # Plain JSON lines, one row per (family, token) in that order: a changed golden shows in a diff.
    return GOLDEN_DIR / f"{version}.jsonl"


def _read_golden(version: str) -> dict[tuple[str, str], dict[str, object]]:
    rows = [json.loads(line) for line in _golden_path(version).read_text().splitlines()]
    return {(row["family"], row["token"]): row for row in rows}


def _compared(name: str, old: dict[str, object], new: dict[str, object]) -> list[str]:
    """Return what a golden row's comparison covers: a version's validity and result columns; every value of
    a two-stage aggregation's row (its weights, stages, parts and summaries, whatever either row holds)."""
    if name.endswith(f".{AGGREGATION}"):
        return sorted((old.keys() | new.keys()) - {"family", "token"})
    return ["valid", *get_version(name).result_columns]


def compare(
    version: str, golden: dict[tuple[str, str], dict[str, object]], rows: list[dict[str, object]]
) -> list[Change]:
    """Return (golden name, family, token, metric, old, new) for every difference above the tolerance; the
    name is a version's, or `<version>.aggregation` for its two-stage split."""
    changes: list[Change] = []
    seen = set()
    for row in rows:
        key = (str(row["family"]), str(row["token"]))
        seen.add(key)
        old = golden.get(key)
        if old is None:
            changes.append((version, *key, "(row)", None, "new"))
            continue
        for metric in _compared(version, old, row):
            before, after = old.get(metric), row.get(metric)
            if isinstance(before, float) and isinstance(after, float):
                if not (abs(before - after) <= TOLERANCE or math.isnan(before) and math.isnan(after)):
                    changes.append((version, *key, metric, before, after))
            elif before != after:
                changes.append((version, *key, metric, before, after))
    changes.extend((version, *key, "(row)", "present", None) for key in golden.keys() - seen)
    return changes


def run_regression(
    update: bool, progress: Callable[[str, int], AbstractContextManager[Callable[[int], None]]]
) -> list[Change]:
    """Score the regression split; rewrite the goldens when `update`, else return the changes."""
    with tempfile.TemporaryDirectory() as work_dir:
        results = compute_results(Path(work_dir), progress)
    changes: list[Change] = []
    for version, rows in results.items():
        if update:
            GOLDEN_DIR.mkdir(parents=True, exist_ok=True)
            ordered = sorted(rows, key=lambda row: (str(row["family"]), str(row["token"])))
            _golden_path(version).write_text(
                "".join(json.dumps(row, sort_keys=True) + "\n" for row in ordered)
            )
            continue
        if not _golden_path(version).exists():
            changes.append(
                (version, "-", "-", "(golden file)", "missing", "run `navsim-lb regress --update`")
            )
            continue
        changes.extend(compare(version, _read_golden(version), rows))
    return changes
