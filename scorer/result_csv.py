"""The devkit's per-token result CSV, written as pandas' `DataFrame.to_csv` writes it, without pandas.

The devkit writes its results with pandas: an unnamed index column (0, 1, ...), `token`, `valid`, the
version's columns and an average row, the column means leaving NaN out (`DataFrame.mean`). Here the same
bytes come from the csv module: floats in Python's shortest round-trip form (what pandas writes), NaN as
an empty field, booleans `True` / `False`. Importing pandas alone takes about 0.3 s, most of a one-token
`navsim-lb score --out`. Beside the devkit's columns, a multi-seed result has a `seed` column (an integer;
empty on the average row) and every result an `error` column.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from scorer.files import write_atomically
from scorer.metrics.aggregation import nan_skipping_mean
from scorer.versions import MetricVersion

if TYPE_CHECKING:
    from scorer.evaluate import TokenResult


def csv_field(value: float | None) -> str:
    """Return a float as pandas writes it in a CSV: its shortest round-trip form, NaN (or None) empty."""
    return "" if value is None or math.isnan(value) else repr(float(value))


def results_csv(results: Sequence[TokenResult], version: MetricVersion) -> str:
    """Return the CSV of per-token results under `version`, with its average row."""
    multi_seed = any(result.seed is not None for result in results)
    columns = version.result_columns
    # A column a result lacks (an unscored token) is NaN, as pandas fills it.
    rows = [[result.metrics.get(column) for column in columns] for result in results]
    values = np.array(
        [[np.nan if value is None else value for value in row] for row in rows], dtype=np.float64
    ).reshape(len(results), len(columns))
    averages = nan_skipping_mean(np.ascontiguousarray(values.T))
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["", "token", *(["seed"] if multi_seed else []), "valid", *columns, "error"])
    for index, (result, row) in enumerate(zip(results, values, strict=True)):
        seed = [str(result.seed) if result.seed is not None else ""] if multi_seed else []
        writer.writerow([index, result.token, *seed, result.valid, *map(csv_field, row), result.error or ""])
    valid = all(result.valid for result in results)
    seed = [""] if multi_seed else []
    writer.writerow([len(results), version.average_row, *seed, valid, *map(csv_field, averages), ""])
    return buffer.getvalue()


def write_results_csv(results: Sequence[TokenResult], version: MetricVersion, path: Path) -> None:
    """Write the CSV of per-token results to `path` (atomically)."""
    write_atomically(Path(path), results_csv(results, version).encode())
