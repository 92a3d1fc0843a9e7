"""The per-token result CSV is what pandas' `DataFrame.to_csv` writes for the devkit's table, byte for byte,
without importing pandas."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from scorer.evaluate import TokenResult
from scorer.metrics.aggregation import defined_mean
from scorer.result_csv import results_csv
from scorer.versions import VERSIONS, MetricVersion


def _pandas_csv(results: list[TokenResult], version: MetricVersion) -> str:
    """The devkit's way: a DataFrame of the rows, the column means (NaN skipped) as the average row."""
    multi_seed = any(result.seed is not None for result in results)
    columns = ["token", *(["seed"] if multi_seed else []), "valid", *version.result_columns, "error"]
    rows = [
        {
            "token": result.token,
            **({"seed": result.seed} if multi_seed else {}),
            "valid": result.valid,
            **{column: result.metrics.get(column, np.nan) for column in version.result_columns},
            "error": result.error or "",
        }
        for result in results
    ]
    frame = pd.DataFrame(rows, columns=columns)
    average = {"token": version.average_row, "valid": bool(frame["valid"].all()), "error": ""}
    average |= {column: frame[column].mean() for column in version.result_columns}
    table = pd.concat([frame, pd.DataFrame([average])], ignore_index=True)
    if multi_seed:  # pandas widens the column to floats for the average row's gap; ours stays integer
        table["seed"] = table["seed"].astype("Int64")
    return table.to_csv()


def _results(version: MetricVersion, count: int, seeds: int, rng: np.random.Generator) -> list[TokenResult]:
    results = []
    for seed in range(seeds):
        for index in range(count):
            token = f"{index:016x}"
            if rng.random() < 0.1:
                results.append(
                    TokenResult(token, seed if seeds > 1 else None, valid=False, error='boom, "quoted"')
                )
                continue
            metrics = {
                column: float(rng.choice([0.0, 0.5, 1.0, rng.random()])) for column in version.result_columns
            }
            if "two_frame_extended_comfort" in metrics and rng.random() < 0.4:
                metrics["two_frame_extended_comfort"] = np.nan  # no frame to pair with
            results.append(TokenResult(token, seed if seeds > 1 else None, valid=True, metrics=metrics))
    return results


@pytest.mark.parametrize("name", sorted(VERSIONS))
@pytest.mark.parametrize(("count", "seeds"), [(1, 1), (7, 1), (300, 1), (40, 3)])
def test_the_csv_is_pandas_to_the_byte(name: str, count: int, seeds: int) -> None:
    version = VERSIONS[name]
    results = _results(version, count, seeds, np.random.default_rng(count * 10 + seeds))
    assert results_csv(results, version) == _pandas_csv(results, version)


def test_writing_the_csv_imports_no_pandas() -> None:
    probe = (
        "import sys; from scorer.evaluate import TokenResult; from scorer.result_csv import results_csv;"
        "from scorer.versions import VERSIONS;"
        "results_csv([TokenResult('a', None, valid=True, metrics={'score': 1.0})], VERSIONS['v1.1']);"
        "print('pandas' in sys.modules)"
    )
    assert (
        subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
        == "False\n"
    )


def test_a_column_mean_leaves_nan_out_as_pandas_does_to_the_bit() -> None:
    """`defined_mean` (summaries, the board) is pandas' mean: NaN replaced by 0 in place, so numpy's pairwise
    sum pairs the values as in the full column; the mean of the defined values alone can differ in the last
    bit, and does on some of these columns."""
    rng = np.random.default_rng(3)
    compacted_differs = 0
    for _ in range(200):
        column = rng.random(rng.integers(9, 400))
        column[rng.random(column.size) < 0.3] = np.nan
        expected = pd.Series(column).mean()
        assert defined_mean(column) == expected
        compacted_differs += column[~np.isnan(column)].mean() != expected
    assert compacted_differs > 0
