"""The summary of a scored submission a person reads in a terminal."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from rich import box
from rich.markup import escape
from rich.table import Table

from scorer.evaluate import TokenResult, summarize
from scorer.versions import METRIC_LABELS, MetricVersion
from server.numbers import percent


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
        for name, reduce in (("mean", np.mean), ("std", np.std), ("max", np.max)):
            rows.append([name, *(percent(value) for value in reduce(values, axis=0)), "", ""])
    return rows


def summary_table(results: Sequence[TokenResult], version: MetricVersion, title: str) -> Table:
    """Return the summary as a table that fits an 80-column terminal (no vertical rules, numbers right)."""
    header, *rows = summary_rows(results, version)
    table = Table(
        title=escape(f"{title} ({version.score_label} {version.name})"),  # plain text: it quotes the method
        caption=f"scores in %; unscored tokens count 0; DDC: {version.ddc_role}"
        + (
            "; EC only between adjacent frames of a log (– where none)"
            if "two_frame_extended_comfort" in version.result_columns
            else ""
        ),
        box=box.SIMPLE_HEAD,
        show_edge=False,
        pad_edge=False,
        # Columns are a space apart (the box's own) and, below 12 columns, one more: "100.0" in every column
        # still fits 80 (v2.2 has thirteen).
        padding=(0, 1, 0, 0) if len(header) < 12 else 0,
    )
    for index, column in enumerate(header):
        table.add_column(column, justify="left" if index == 0 else "right", no_wrap=True)
    for row in rows:
        table.add_row(*row)
    return table
