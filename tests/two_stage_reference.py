"""The official per-token values of the two-stage reference excerpt, as the aggregation's input."""

from __future__ import annotations

import csv
import gzip
import json
from pathlib import Path
from typing import Any

from scorer.evaluate import TokenResult
from scorer.two_stage.aggregate import SCORE_COLUMNS, TwoStageToken
from scorer.two_stage.split import read_two_stage_split

FIXTURE = Path(__file__).parent / "fixtures" / "epdms-two-stage"
FAMILIES = sorted(path.name.split(".")[0] for path in (FIXTURE / "expected").glob("*.csv"))
SPLIT = read_two_stage_split(FIXTURE / "two_stage.json")


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
