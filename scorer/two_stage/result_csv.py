"""The official two-stage result CSV, byte for byte, without pandas (docs/engine.md, "Two-stage EPDMS").

The official script writes with `DataFrame.to_csv`: an unnamed index column (0, 1, ...), `token`, `valid`,
each score column as `<column>_stage_one` (rows of logged frames) and `<column>_stage_two` (synthetic
frames; a failed row has no frame type and fills neither), and `score` (the row's, whichever stage); the
rows in submission order, then `extended_pdm_score_stage_one` (its stage-one columns and score),
`extended_pdm_score_stage_two` (its stage-two columns and score) and `extended_pdm_score_combined` (both
stages' means, and the combined score). Floats are Python's shortest round-trip repr, NaN an empty field,
booleans `True` / `False`, lines end in a newline.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

from scorer.files import write_atomically
from scorer.result_csv import csv_field
from scorer.two_stage.aggregate import SCORE_COLUMNS, TwoStageResult, stage_of

STAGE_COLUMNS = tuple(column for column in SCORE_COLUMNS if column != "score")
STAGE_SUFFIXES = ("_stage_one", "_stage_two")
HEADER = (
    "",
    "token",
    "valid",
    *(f"{column}{suffix}" for suffix in STAGE_SUFFIXES for column in STAGE_COLUMNS),
    "score",
)
SUMMARY_TOKENS = (
    "extended_pdm_score_stage_one",
    "extended_pdm_score_stage_two",
    "extended_pdm_score_combined",
)


def _stage_fields(values: dict[str, float] | None) -> list[str]:
    return [csv_field(values[column]) if values is not None else "" for column in STAGE_COLUMNS]


def two_stage_csv(result: TwoStageResult) -> str:
    """Return the official CSV of a two-stage result."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(HEADER)
    for index, row in enumerate(result.rows):
        stage = stage_of(row)
        writer.writerow(
            [
                index,
                row.token,
                row.valid,
                *_stage_fields(row.metrics if stage == 1 else None),
                *_stage_fields(row.metrics if stage == 2 else None),
                csv_field(row.metrics["score"]) if stage is not None else "",
            ]
        )
    summaries = (
        (result.stage_one, None, result.stage_one["score"]),
        (None, result.stage_two, result.stage_two["score"]),
        (result.stage_one, result.stage_two, result.combined["score"]),
    )
    for offset, (token, (stage_one, stage_two, score)) in enumerate(
        zip(SUMMARY_TOKENS, summaries, strict=True)
    ):
        writer.writerow(
            [
                len(result.rows) + offset,
                token,
                result.official,
                *_stage_fields(stage_one),
                *_stage_fields(stage_two),
                csv_field(score),
            ]
        )
    return buffer.getvalue()


def write_two_stage_csv(result: TwoStageResult, path: Path) -> None:
    """Write the official CSV of a two-stage result to `path` (atomically)."""
    write_atomically(Path(path), two_stage_csv(result).encode())
