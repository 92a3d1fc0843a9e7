"""Comfort filters: the engine's batch filtering against scipy's call on the devkit's groups of proposals.

The devkit filters a token's proposals together (2 in evaluation, 15 in PDM-Closed) with
`scipy.signal.savgol_filter` and rounds every output to 8 decimals; the engine filters a whole batch at
once and filters a token again as a group when an output lies too close to a rounding midpoint
(docs/engine.md, "Comfort filters"). On random groups with the magnitudes of real accelerations and
headings this prints:
- the largest distance of a batch edge output from the group call's, in units of eps * sum |x_i M_ij|
  (the bound `savgol.EDGE_ERROR_ULPS` must exceed it);
- how many rounded outputs of the batch filtering alone differ from the group call's;
- how many tokens the engine filtered again, and how many of its rounded outputs differ (must be 0).
Usage: .venv/bin/python benchmarks/comfort_rounding.py [--groups 3000] [--size 2] [--seed 0]
"""

from __future__ import annotations

import scorer  # noqa: F401 - before numpy: it selects the official results' OpenBLAS kernels

# isort: split

import argparse
import time

import numpy as np
from scipy.signal import savgol_filter

from scorer.metrics import comfort
from scorer.metrics.savgol import EDGE_ERROR_ULPS, filter_batch, savgol_operator
from scorer.trajectory import SCORING_INTERVAL_S

NUM_STEPS = 41
EPS = float(np.finfo(np.float64).eps)


def _random_groups(rng: np.random.Generator, groups: int, size: int) -> np.ndarray:
    """Return comfort series (groups, size, 41, 4): smooth accelerations with jitter, drifting headings."""
    shape = (groups, size, NUM_STEPS)
    time_s = np.arange(NUM_STEPS) * SCORING_INTERVAL_S
    lon = rng.normal(0, 1.5, (*shape[:2], 1)) + np.cumsum(rng.normal(0, 0.3, shape), axis=-1)
    lat = rng.normal(0, 1.0, (*shape[:2], 1)) * np.sin(time_s * rng.uniform(0.2, 2.0, (*shape[:2], 1)))
    heading = rng.uniform(-np.pi, np.pi, (*shape[:2], 1)) + np.cumsum(rng.normal(0, 0.02, shape), axis=-1)
    return np.stack([lon, lat, heading, np.hypot(lon, lat)], axis=-1)


def _scipy_rounded(group: np.ndarray, window: int, poly_order: int, deriv: int, delta: float) -> np.ndarray:
    """The devkit's call: one `savgol_filter` of a token's proposals, rounded to 8 decimals."""
    window = min(window, group.shape[-1])
    filtered = savgol_filter(group, window_length=window, polyorder=poly_order, deriv=deriv, delta=delta)
    return np.round(filtered, comfort.DECIMALS)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--groups", type=int, default=3000)
    parser.add_argument("--size", type=int, default=2, help="proposals filtered together (2 or 15)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    series = _random_groups(np.random.default_rng(args.seed), args.groups, args.size)
    delta = SCORING_INTERVAL_S

    worst_ulps, batch_differences, values = 0.0, 0, 0

    def batch_alone(group: np.ndarray, window: int, poly_order: int, deriv: int, step: float) -> np.ndarray:
        nonlocal worst_ulps, batch_differences, values
        window = min(window, group.shape[-1])
        filtered, _ = filter_batch(group, window, poly_order, deriv, step)
        exact = savgol_filter(group, window_length=window, polyorder=poly_order, deriv=deriv, delta=step)
        scale = np.abs(group) @ np.abs(savgol_operator(group.shape[-1], window, poly_order, deriv, step))
        with np.errstate(invalid="ignore"):
            worst_ulps = max(worst_ulps, float(np.nanmax(np.abs(filtered - exact) / (EPS * scale))))
        rounded = np.round(filtered, comfort.DECIMALS)
        batch_differences += int(np.count_nonzero(rounded != np.round(exact, comfort.DECIMALS)))
        values += rounded.size
        return np.round(exact, comfort.DECIMALS)  # the next stage starts from the devkit's values

    start = time.perf_counter()
    for group in series:
        comfort._filtered_series(group, delta, batch_alone)
    print(
        f"{args.groups} groups of {args.size}, {values} rounded outputs ({time.perf_counter() - start:.0f} s):"
        f" batch edges within {worst_ulps:.1f} eps * sum |x M| of the group call's"
        f" (bound {EDGE_ERROR_ULPS});"
        f" {batch_differences} rounded outputs of the batch alone differ"
    )

    start = time.perf_counter()
    outputs, regrouped = comfort.filtered_series(series, SCORING_INTERVAL_S)
    engine_seconds = time.perf_counter() - start
    expected = [
        np.stack(stage)
        for stage in zip(*(comfort._filtered_series(g, delta, _scipy_rounded) for g in series), strict=True)
    ]
    differing = sum(
        int(np.count_nonzero(ours != devkit)) for ours, devkit in zip(outputs, expected, strict=True)
    )
    print(
        f"engine: {int(regrouped.sum())} of {args.groups} tokens filtered again as a group"
        f" ({100 * regrouped.mean():.2f}%), {differing} rounded outputs differ from the devkit's call"
        f" ({1e6 * engine_seconds / args.groups:.0f} us per token)"
    )


if __name__ == "__main__":
    main()
