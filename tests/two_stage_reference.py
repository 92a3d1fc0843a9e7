"""The official per-token values of the two-stage reference excerpt, as the aggregation's input."""

from __future__ import annotations

import csv
import gzip
import json
import math
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from scorer.evaluate import TokenResult
from scorer.submission import SubmissionMetadata, TwoStageSubmission
from scorer.two_stage.aggregate import GROUP_PARTS, SCORE_COLUMNS, TwoStageResult, TwoStageToken
from scorer.two_stage.split import load_two_stage_split, read_two_stage_split

FIXTURE = Path(__file__).parent / "fixtures" / "epdms-two-stage"
FAMILIES = sorted(path.name.split(".")[0] for path in (FIXTURE / "expected").glob("*.csv"))
SPLIT = read_two_stage_split(FIXTURE / "two_stage.json")
# The excerpt the server's tests score: 3 groups of the reference (36 tokens), the families' submitted poses.
EXCERPT = Path(__file__).parent / "fixtures" / "epdms-two-stage-reactive"
EXCERPT_STAGES = load_two_stage_split(EXCERPT)


def official_tokens(family: str) -> dict[str, dict[str, Any]]:
    """Return token -> the official per-token line of `family`."""
    with gzip.open(FIXTURE / "expected" / f"{family}.tokens.jsonl.gz", "rt") as lines:
        return {line["token"]: line for line in map(json.loads, lines)}


def official_row_order(family: str) -> list[str]:
    """Return the tokens in the official CSV's row order (the submission's: stage one, then stage two)."""
    with (FIXTURE / "expected" / f"{family}.csv").open(newline="") as file:
        return [row["token"] for row in csv.DictReader(file)][:-3]


def official_summary(family: str) -> dict[str, Any]:
    summary: dict[str, Any] = json.loads((FIXTURE / "expected" / f"{family}.summary.json").read_text())
    return summary


def aggregation_input(family: str) -> list[TwoStageToken]:
    """Return the official per-token results of `family` in row order, as the aggregation reads them."""
    lines = official_tokens(family)
    return [
        TwoStageToken(
            result=TokenResult(
                token=token,
                seed=None,
                valid=lines[token]["valid"],
                metrics={column: lines[token][column] for column in SCORE_COLUMNS},
            ),
            start_point=tuple(lines[token]["start_point"]),
            endpoint=tuple(lines[token]["endpoint"]),
        )
        for token in official_row_order(family)
    ]


def _same(actual: float, expected: float | None) -> bool:
    """Bit equality, NaN (None in JSON) equal to NaN."""
    if expected is None:
        return math.isnan(actual)
    return actual == expected


def token_mismatches(result: TwoStageResult, lines: dict[str, dict[str, Any]]) -> list[str]:
    """Return how the scored rows of `result` differ from the official lines: every column, the weight and
    how it came about, and the two-frame comfort's partner and RMS differences (`ec_detail`)."""
    found = []
    for row in result.rows:
        line = lines[row.token]
        if not row.valid:
            found.append(f"{row.token}: invalid ({row.error})")
            continue
        found += [
            f"{row.token}: {column} {row.metrics[column]!r} != {line[column]!r}"
            for column in SCORE_COLUMNS
            if not _same(row.metrics[column], line[column])
        ]
        if result.weights.get(row.token) != line["weight"]:
            found.append(f"{row.token}: weight {result.weights.get(row.token)!r} != {line['weight']!r}")
        if line["stage"] == "two" and result.weight_detail.get(row.token) != line["weight_detail"]:
            found.append(f"{row.token}: weight detail {result.weight_detail.get(row.token)}")
        comfort = row.detail["two_frame_extended_comfort"]
        partner = comfort.get("previous_token", comfort.get("current_token"))
        official = line["ec_detail"]
        if (partner, comfort.get("rms")) != (official["partner"], official["ec_rms"]):
            found.append(f"{row.token}: EC partner and RMS {partner} {comfort.get('rms')} != {official}")
    return found


def group_mismatches(result: TwoStageResult, groups: list[dict[str, Any]]) -> list[str]:
    """Return how the groups of `result` differ from the official ones (the first len(result.groups)): the
    four weighted averages of every column and the group's combined score."""
    found = []
    for group, expected in zip(result.groups, groups, strict=False):
        if (group.original, group.previous) != (expected["original"], expected["previous"]):
            found.append(f"group {group.original}: official group {expected['original']}")
            continue
        for part, columns in zip(GROUP_PARTS, expected["columns"], strict=True):
            found += [
                f"group {group.original} {part} {column}: {group.parts[part][column]!r} != {columns[column]!r}"
                for column in SCORE_COLUMNS
                if not _same(group.parts[part][column], columns[column])
            ]
        if group.combined["score"] != expected["combined"]:
            found.append(f"group {group.original}: {group.combined['score']!r} != {expected['combined']!r}")
    return found


@cache
def family_poses(family: str) -> dict[str, np.ndarray]:
    """Return a reference family's submitted poses of the 36 excerpt tokens."""
    with gzip.open(EXCERPT / "predictions.json.gz", "rt") as handle:
        predictions: dict[str, dict[str, Any]] = json.load(handle)
    return {token: np.array(poses) for token, poses in predictions[family].items()}


def family_submission(family: str, seeds: int = 1) -> TwoStageSubmission:
    """Return a family's two-stage submission of the excerpt; seed i > 0 moves every pose i x 0.3 m ahead."""
    poses = family_poses(family)
    shifted = [
        {token: value + [0.3 * seed, 0.0, 0.0] for token, value in poses.items()} for seed in range(seeds)
    ]
    first, second = (
        tuple({token: seed[token] for token in tokens} for seed in shifted)
        for tokens in (EXCERPT_STAGES.stage_one_tokens, EXCERPT_STAGES.stage_two_tokens)
    )
    return TwoStageSubmission(SubmissionMetadata(method=family), first, second)
