"""The Savitzky-Golay filters against the installed scipy, bit for bit: ndimage's convolution, scipy's dgelsd
solve, a group's filter and the filter of the identity; under this process's OpenBLAS kernels and the Haswell
ones; and on every filter call the engine makes while it caches and scores reference scenes."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from engine_scoring import score_caches
from scipy.linalg import lstsq
from scipy.ndimage import convolve1d
from scipy.signal import savgol_coeffs, savgol_filter

from scorer.blas import KEEP_VARIABLE
from scorer.cache import build_caches
from scorer.metrics import comfort
from scorer.metrics.savgol import (
    _coefficients,
    _convolve_inside,
    _lstsq,
    _pair_combination,
    filter_batch,
    savgol_operator,
)
from scorer.metrics.savgol import savgol_filter as savgol_filter_of_group
from scorer.scene import load_scene, scene_paths
from scorer.submission import load_submission
from scorer.versions import VERSIONS

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
EPS = float(np.finfo(np.float64).eps)

# (n, window, poly_order, deriv, delta): the comfort metric's filters at 41 states and 0.1 s, then others
# (even and odd windows, a window as long as the series, second derivatives, other spacings).
CASES = [
    (41, 41, 2, 0, 1.0),
    (41, 8, 2, 0, 1.0),
    (41, 41, 2, 1, 0.1),
    (41, 5, 3, 2, 0.1),
    (41, 5, 2, 1, 0.1),
    (20, 15, 2, 1, 0.5),
    (9, 4, 3, 3, 0.25),
    (5, 5, 2, 2, 1.0),
    (12, 3, 1, 0, 2.0),
]


def assert_same_bits(actual: np.ndarray, expected: np.ndarray) -> None:
    """Equal bit for bit: -0.0 is not 0.0 here, as it is for `assert_array_equal`."""
    assert actual.shape == expected.shape and actual.dtype == expected.dtype == np.float64
    different = actual.view(np.uint64) != expected.view(np.uint64)
    assert not different.any(), f"{different.sum()} of {different.size} differ: {actual[different][:5]}"


@pytest.mark.parametrize(("num_steps", "window", "poly_order", "deriv", "delta"), CASES)
def test_operator_is_scipys_filter_of_the_identity(
    num_steps: int, window: int, poly_order: int, deriv: int, delta: float
) -> None:
    expected = savgol_filter(
        np.eye(num_steps), window_length=window, polyorder=poly_order, deriv=deriv, delta=delta, axis=-1
    )
    assert_same_bits(savgol_operator(num_steps, window, poly_order, deriv, delta), expected)


def test_operator_applied_to_a_series_is_the_filter_of_the_series() -> None:
    series = np.random.default_rng(3).normal(size=(6, 41))
    filtered = savgol_filter(series, window_length=8, polyorder=2, axis=-1)
    np.testing.assert_allclose(series @ savgol_operator(41, 8, 2, 0, 1.0), filtered, rtol=0, atol=1e-13)


@pytest.mark.parametrize("group_size", [1, 2, 15])
@pytest.mark.parametrize(("num_steps", "window", "poly_order", "deriv", "delta"), CASES)
def test_group_filter_is_scipys_call_on_the_group(
    group_size: int, num_steps: int, window: int, poly_order: int, deriv: int, delta: float
) -> None:
    rng = np.random.default_rng(group_size * 100 + window)
    for _ in range(20):
        group = rng.normal(0, 3, (group_size, num_steps)) * rng.uniform(0.01, 100, (group_size, 1))
        expected = savgol_filter(group, window_length=window, polyorder=poly_order, deriv=deriv, delta=delta)
        assert_same_bits(savgol_filter_of_group(group, window, poly_order, deriv, delta), expected)


def test_batch_filter_is_exact_inside_and_bounded_at_the_edges() -> None:
    rng = np.random.default_rng(9)
    series = rng.normal(0, 3, (200, 41)) + rng.uniform(-4, 4, (200, 1))
    for window, poly_order, deriv, delta in [(41, 2, 0, 1.0), (8, 2, 0, 1.0), (5, 3, 2, 0.1)]:
        filtered, error = filter_batch(series, window, poly_order, deriv, delta)
        expected = np.concatenate(
            [savgol_filter_of_group(pair, window, poly_order, deriv, delta) for pair in np.split(series, 100)]
        )
        interior = error == 0
        assert interior.sum() == 200 * (41 - 2 * (window // 2))
        np.testing.assert_array_equal(filtered[interior], expected[interior])
        assert (np.abs(filtered - expected) <= error / 4).all()  # with room to spare


def _weights(rng: np.random.Generator) -> Iterator[np.ndarray]:
    """Coefficients of every kind ndimage tells apart: the engine's filters' (symmetric or antisymmetric
    within DBL_EPSILON, or even), exactly and nearly (anti)symmetric ones, ones just beyond the tolerance."""
    for _, window, poly_order, deriv, delta in CASES:
        yield _coefficients(window, poly_order, deriv, delta)
    for size in (1, 2, 3, 4, 5, 8, 9, 15, 40, 41):
        yield rng.normal(size=size)
    for half in (1, 2, 7, 20):
        side = 0.1 * rng.normal(size=half)  # ulps well below DBL_EPSILON: the nudges below stay apart
        for centre in (0.0, rng.normal()):
            for sign in (1.0, -1.0):
                exact = np.concatenate([side, [centre], sign * side[::-1]])
                yield exact
                for offset in (0.5 * EPS, EPS, 1.5 * EPS):  # within, at and beyond the tolerance
                    nudged = exact.copy()
                    nudged[-1] += offset
                    yield nudged


def test_convolution_is_ndimages() -> None:
    rng = np.random.default_rng(5)
    orders = set()
    for weights in _weights(rng):
        orders.add(_pair_combination(weights[::-1]))
        half = weights.size // 2
        for num_steps in (weights.size, weights.size + 1, weights.size + 30):
            series = rng.normal(0, 3, (4, 3, num_steps)) * rng.choice([1e-9, 1.0, 1e6], (4, 3, 1))
            series[0, 0] = 0.0
            series[0, 1, ::2] = -0.0  # signed zeros must come out as ndimage's
            expected = convolve1d(series, weights, axis=-1, mode="constant")[..., half : num_steps - half]
            assert_same_bits(_convolve_inside(series, weights), expected)
    assert orders == {np.add, np.subtract, None}  # ndimage's three summation orders


def _systems(rng: np.random.Generator) -> Iterator[tuple[np.ndarray, np.ndarray, float]]:
    """(lhs, rhs, cond): savgol_coeffs' wide systems, polyfit's tall scaled Vandermonde ones, random ones."""
    for _, window, poly_order, deriv, delta in CASES:
        offsets = np.arange(window, dtype=np.float64)[::-1] - (window - 1) / 2
        design = offsets ** np.arange(poly_order + 1, dtype=np.float64).reshape(-1, 1)
        target = np.zeros(poly_order + 1)
        target[deriv] = 1.0 / delta**deriv
        yield design, target, EPS * window
    for window in (3, 4, 5, 8, 15, 41, 55):
        for poly_order in (0, 1, 2, 3):
            vandermonde = np.arange(window, dtype=np.float64)[:, None] ** np.arange(poly_order, -1, -1.0)
            vandermonde /= np.sqrt(np.sum(vandermonde * vandermonde, axis=0))
            for columns in (1, 2, 15, 41):
                yield (
                    vandermonde,
                    rng.normal(0, 3, (window, columns)) * rng.uniform(0.01, 100, columns),
                    window * EPS,
                )
            yield vandermonde, np.eye(window, 41), window * EPS
            yield vandermonde, rng.normal(size=window), window * EPS
    for rows, columns in ((6, 6), (9, 4), (4, 9), (2, 30)):
        yield rng.normal(size=(rows, columns)), rng.normal(size=(rows, 3)), 1e-10


def test_least_squares_solve_is_scipys() -> None:
    for lhs, rhs, cond in _systems(np.random.default_rng(7)):
        assert_same_bits(_lstsq(lhs, rhs, cond), lstsq(lhs, rhs, cond=cond)[0])


def _scipys_batch_filter(
    series: np.ndarray, window: int, poly_order: int, deriv: int, delta: float
) -> np.ndarray:
    """What `filter_batch` must give: scipy's convolution inside, scipy's filter of the identity at the edges."""
    filtered = convolve1d(series, savgol_coeffs(window, poly_order, deriv, delta), axis=-1, mode="constant")
    num_steps, half = series.shape[-1], window // 2
    operator = savgol_filter(np.eye(num_steps), window, poly_order, deriv, delta)
    for edge in (slice(0, half), slice(num_steps - half, num_steps)):
        filtered[..., edge] = series @ operator[:, edge]
    return filtered


def _recording(
    calls: list[tuple[str, np.ndarray, tuple[Any, ...], Any]], kind: str, filter_: Callable
) -> Callable:
    def recorded(series: np.ndarray, *arguments: Any) -> Any:
        output = filter_(series, *arguments)
        calls.append((kind, series.copy(), arguments, output))
        return output

    return recorded


def test_every_filter_call_of_caching_and_scoring_reference_scenes_is_scipys(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """PDM-Closed's 15 proposals when caching, every version's pairs and histories when scoring: the engine's
    real inputs, of which a few tokens' are filtered again as groups."""
    calls: list[tuple[str, np.ndarray, tuple[Any, ...], Any]] = []
    monkeypatch.setattr(comfort, "filter_batch", _recording(calls, "batch", comfort.filter_batch))
    monkeypatch.setattr(comfort, "savgol_filter", _recording(calls, "group", comfort.savgol_filter))
    paths = list(scene_paths(REFERENCE).values())[:12]
    caches = [build_caches(load_scene(path), list(VERSIONS.values())) for path in paths]
    for family in ("human_noise", "zigzag", "hard_brake", "swerve_left"):
        file = REFERENCE / "submissions" / f"{family}.json"
        poses = load_submission(file.read_bytes(), file.name).seeds[0]
        for version in VERSIONS:
            scored = [cache[version] for cache in caches]
            score_caches(scored, [poses[cache.token] for cache in scored], VERSIONS[version])
    assert sum(kind == "group" for kind, *_ in calls) >= 10  # tokens near a rounding midpoint
    for kind, series, arguments, output in calls:
        if kind == "batch":
            assert_same_bits(output[0], _scipys_batch_filter(series, *arguments))
        else:
            window, poly_order, deriv, delta = arguments
            assert_same_bits(output, savgol_filter(series, window, poly_order, deriv, delta))


RUN_UNDER_OTHER_KERNELS = """
import sys
import pytest
import scorer
from scorer.blas import blas_kernels
print("kernels:", *blas_kernels(), flush=True)
sys.exit(pytest.main(["-q", "-p", "no:cacheprovider", "-k", "not other_kernels", sys.argv[1]]))
"""


def test_every_test_here_passes_under_other_kernels() -> None:
    """dgelsd's bits depend on the kernels (the Haswell ones change most solutions): the engine's solve must
    follow scipy's under them too, in a fresh process since OpenBLAS picks its kernels when it loads."""
    done = subprocess.run(
        [sys.executable, "-c", RUN_UNDER_OTHER_KERNELS, __file__],
        capture_output=True,
        text=True,
        check=False,
        env={**os.environ, "OPENBLAS_CORETYPE": "Haswell", KEEP_VARIABLE: "1"},
    )
    kernels = next(
        (line.split()[1:] for line in done.stdout.splitlines() if line.startswith("kernels:")), None
    )
    assert kernels is not None, done.stderr[-3000:]
    if kernels != ["Haswell"]:
        pytest.skip(f"this CPU cannot run OpenBLAS's Haswell kernels (it ran {kernels})")
    assert done.returncode == 0, done.stdout[-3000:]
