"""Result tables: the devkit's per-token CSV layout and the terminal summary."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from scorer.evaluate import TokenResult, summarize
from scorer.versions import MetricVersion


def results_table(results: Sequence[TokenResult], version: MetricVersion) -> pd.DataFrame:
    """Return the devkit's CSV table: token, valid, the version's columns, an `error`, and an `average` row.

    As in the devkit, the average row is the column mean over valid rows and its `valid` is all(valid);
    a `seed` column is added only for multi-seed results.
    """
    multi_seed = any(result.seed is not None for result in results)
    rows = []
    for result in results:
        row: dict[str, object] = {"token": result.token}
        if multi_seed:
            row["seed"] = result.seed
        row["valid"] = result.valid
        row.update({column: result.metrics.get(column, np.nan) for column in version.result_columns})
        row["error"] = result.error or ""
        rows.append(row)
    frame = pd.DataFrame(
        rows, columns=["token", *(["seed"] if multi_seed else []), "valid", *version.result_columns, "error"]
    )
    average: dict[str, object] = {"token": "average", "valid": bool(frame["valid"].all()), "error": ""}
    average.update({column: frame[column].mean() for column in version.result_columns})
    return pd.concat([frame, pd.DataFrame([average])], ignore_index=True)


def summary_rows(results: Sequence[TokenResult], version: MetricVersion) -> list[list[str]]:
    """Return a header and rows: per seed the mean (unscored tokens count 0), then mean/std/max over seeds."""
    seeds = sorted({result.seed for result in results}, key=lambda seed: -1 if seed is None else seed)
    per_seed = {seed: summarize([r for r in results if r.seed == seed]) for seed in seeds}
    columns = list(version.result_columns)
    header = ["seed", *columns, "tokens", "unscored"]
    rows = [header]
    for seed, summary in per_seed.items():
        rows.append(
            [
                "-" if seed is None else str(seed),
                *(f"{summary[c]:.6f}" for c in columns),
                f"{summary['tokens']:.0f}",
                f"{summary['failed']:.0f}",
            ]
        )
    if len(seeds) > 1:
        values = np.array([[per_seed[seed][c] for c in columns] for seed in seeds])
        for name, reduce in (("mean", np.mean), ("std", np.std), ("max", np.max)):
            rows.append([name, *(f"{v:.6f}" for v in reduce(values, axis=0)), "", ""])
    return rows
