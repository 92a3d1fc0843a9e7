"""Aggregation of the metric rows into the PDM Score (docs/engine.md, "Metrics")."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from scorer.geometry import FloatArray


def aggregate(multipliers: FloatArray, weighted: FloatArray, weights: FloatArray) -> FloatArray:
    """Return score (...) = product of the multiplier rows (m, ...) x weighted mean of the rows (w, ...).

    The rows are summed in order and divided by the weight sum afterwards, as the devkit does.
    """
    row_weights = weights.reshape(-1, *[1] * (weighted.ndim - 1))
    weighted_mean = (weighted * row_weights).sum(axis=0) / weights.sum()
    return multipliers.prod(axis=0) * weighted_mean


def defined_mean(values: npt.ArrayLike) -> float:
    """Return the mean of the defined values of a column (flattened), NaN if none is: a column's mean over
    tokens, which leaves out v2.2's undefined EC as the devkit's average row does, to the bit
    (`nan_skipping_mean`)."""
    return float(nan_skipping_mean(np.ascontiguousarray(values, dtype=np.float64).reshape(-1)))


def nan_skipping_mean(values: FloatArray) -> FloatArray:
    """Return the mean over the last axis leaving NaN out, as pandas' `DataFrame.mean()` (the devkit's summary
    rows): NaN is replaced by 0 in place, so that numpy's pairwise sum pairs the other values as in the full
    column (not as in the defined values alone), and the sum is divided by the count of defined values; NaN
    where none is."""
    defined = ~np.isnan(values)
    count = defined.sum(axis=-1)
    total = np.ascontiguousarray(np.where(defined, values, 0.0)).sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)
