"""The summary of a scored submission a person reads in a terminal or a log (drawn by `print_table`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from navsim_lb.terminal import TextTable
from scorer.evaluate import TokenResult, summarize
from scorer.versions import METRIC_LABELS, MetricVersion
from server.numbers import percent

if TYPE_CHECKING:  # the two-stage engine loads only where a two-stage version is scored (start-up)
    from scorer.two_stage.aggregate import TwoStageResult

OVER_SEEDS = (("mean", np.mean), ("std", np.std), ("max", np.max))


def summary_rows(results: Sequence[TokenResult], version: MetricVersion) -> list[list[str]]:
    """Return a header and rows: per seed the mean (unscored tokens count 0), then mean/std/max over seeds.

    Headers are the short metric names (NC, DAC, ..., PDMS) and scores are percent, as on the leaderboard.
    """
    seeds = sorted({result.seed for result in results}, key=lambda seed: -1 if seed is None else seed)
    columns = list(version.result_columns)
    per_seed = {seed: summarize([r for r in results if r.seed == seed], columns) for seed in seeds}
    labels = [version.score_label if column == "score" else METRIC_LABELS[column] for column in columns]
    rows = [["seed", *labels, "tokens", "unscored"]]
    for seed, summary in per_seed.items():
        rows.append(
            [
                "-" if seed is None else str(seed),
                *(percent(summary[column]) for column in columns),
                f"{summary['tokens']:.0f}",
                f"{summary['failed']:.0f}",
            ]
        )
    if len(seeds) > 1:
        values = np.array([[per_seed[seed][column] for column in columns] for seed in seeds])
        for name, reduce in OVER_SEEDS:
            rows.append([name, *(percent(value) for value in reduce(values, axis=0)), "", ""])
    return rows


def summary_table(results: Sequence[TokenResult], version: MetricVersion, title: str) -> TextTable:
    """Return the summary as a table that fits an 80-column terminal (no vertical rules, numbers right)."""
    caption = f"scores in %; unscored tokens count 0; DDC: {version.ddc_role}" + (
        "; EC only between adjacent frames of a log (– where none)"
        if "two_frame_extended_comfort" in version.result_columns
        else ""
    )
    return TextTable(
        f"{title} ({version.score_label} {version.name})", caption, summary_rows(results, version)
    )


def two_stage_summary_rows(results: Sequence[TwoStageResult], version: MetricVersion) -> list[list[str]]:
    """Return a header and rows of a two-stage result: per seed the stage-one, stage-two and combined score
    (the reported one), the groups scored, the unscored tokens and whether the official script would have
    given these numbers; then mean/std/max over seeds. Scores are percent, "–" where undefined."""
    rows = [["seed", "stage one", "stage two", version.score_label, "groups", "unscored", "official"]]
    scores = np.array(
        [[result.stage_one["score"], result.stage_two["score"], result.score] for result in results]
    )
    for index, result in enumerate(results):
        rows.append(
            [
                str(index) if len(results) > 1 else "-",
                *(percent(value) for value in scores[index]),
                str(len(result.groups)),
                str(sum(not row.valid for row in result.rows)),
                "yes" if result.official else "no",
            ]
        )
    if len(results) > 1:
        for name, reduce in OVER_SEEDS:
            rows.append([name, *(percent(value) for value in reduce(scores, axis=0)), "", "", ""])
    return rows


def two_stage_summary_table(
    results: Sequence[TwoStageResult], version: MetricVersion, title: str
) -> TextTable:
    """Return the two-stage summary as a table for a terminal (`two_stage_summary_rows`)."""
    caption = "scores in %; official: the official script gives these numbers (if not, the warnings say why)"
    return TextTable(
        f"{title} ({version.score_label} {version.name})", caption, two_stage_summary_rows(results, version)
    )
