"""The official per-token values of the two-stage reference excerpt, as the aggregation's input."""

from __future__ import annotations

import csv
import gzip
import json
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from devkit_kernels import CONTINUOUS_TOLERANCE, devkit_tolerance, same_number, same_values

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
# EC's RMS differences are of the simulated states' derivatives up to the third (jerk: x1000 at 10 Hz), where
# the last bits other kernels move in the states grew to 3.3e-9 on the whole reference (devkit_kernels).
RMS_TOLERANCE = devkit_tolerance(1e-7)


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


def csv_mismatches(ours: str, official: str) -> list[str]:
    """Return where our CSV differs from the official one: byte for byte under the official kernels; under
    others each cell's text exactly or, both numbers, within CONTINUOUS_TOLERANCE."""
    if ours == official or not CONTINUOUS_TOLERANCE:
        return [] if ours == official else ["the CSV is not the official one byte for byte"]
    ours_rows, official_rows = (list(csv.reader(text.splitlines())) for text in (ours, official))
    if [len(row) for row in ours_rows] != [len(row) for row in official_rows]:
        return ["the CSV's rows and columns are not the official ones"]
    return [
        f"row {index} column {column}: {cell!r} != {expected!r}"
        for index, (row, official_row) in enumerate(zip(ours_rows, official_rows, strict=True))
        for column, (cell, expected) in enumerate(zip(row, official_row, strict=True))
        if cell != expected and not _numbers_within(cell, expected)
    ]


def _numbers_within(cell: str, expected: str) -> bool:
    try:
        return abs(float(cell) - float(expected)) <= CONTINUOUS_TOLERANCE
    except ValueError:
        return False


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
            if not same_number(row.metrics[column], line[column])
        ]
        if result.weights.get(row.token) != line["weight"]:
            found.append(f"{row.token}: weight {result.weights.get(row.token)!r} != {line['weight']!r}")
        if line["stage"] == "two" and result.weight_detail.get(row.token) != line["weight_detail"]:
            found.append(f"{row.token}: weight detail {result.weight_detail.get(row.token)}")
        comfort = row.detail["two_frame_extended_comfort"]
        partner = comfort.get("previous_token", comfort.get("current_token"))
        official = line["ec_detail"]
        if partner != official["partner"] or not same_values(
            comfort.get("rms"), official["ec_rms"], RMS_TOLERANCE
        ):
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
                if not same_number(group.parts[part][column], columns[column])
            ]
        if not same_number(group.combined["score"], expected["combined"]):
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
