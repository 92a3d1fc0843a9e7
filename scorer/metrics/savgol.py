"""Savitzky-Golay filters computed as scipy 1.17's `savgol_filter(mode="interp")` computes them, without
importing scipy.

The comfort metric filters every series with `scipy.signal.savgol_filter`. Its outputs come from two
computations:

- inside the series, a convolution (`scipy.ndimage.convolve1d`, each series on its own), whose sums ndimage
  adds in an order of its own (`_convolve_inside` reproduces it);
- in the first and last window // 2 outputs, polynomials fitted to the first or last `window` samples by
  one LAPACK least-squares solve (`scipy.linalg.lstsq`, dgelsd) over every series of the call. That solve's
  last bits depend on how many series share it, so only a call on the very same group of series
  reproduces the devkit's bits there (docs/engine.md, "Comfort filters"); they also depend on the library,
  its kernels and the work size, so `_lstsq` makes scipy's very dgelsd call in SciPy's own OpenBLAS
  (`scorer.blas.scipy_openblas`). The convolution's coefficients come from the same solve, as in
  `savgol_coeffs`.

`savgol_filter` makes scipy's calls on a group, bit-identical to scipy (`tests/test_metrics_savgol.py`);
`filter_batch` filters any number of series at once: the convolution exactly, the edges through the
filter's matrix (the filter of the identity) with a bound on their distance from any group's fit. Neither
imports scipy: `scipy.linalg` and `scipy.ndimage` cost about 0.2 s at start-up, `scipy.signal` 0.6 s more
(docs/engine.md, "Start-up").
"""

from __future__ import annotations

import ctypes
import math
from collections.abc import Callable
from functools import cache

import numpy as np
import numpy.typing as npt

from scorer.blas import scipy_lapack_function
from scorer.geometry import FloatArray

_EPS = float(np.finfo(np.float64).eps)  # also C's DBL_EPSILON, ndimage's symmetry tolerance


def _ints(*values: int) -> npt.NDArray[np.intc]:
    """Fortran INTEGERs: SciPy's OpenBLAS is the 32-bit-integer (LP64) build."""
    return np.array(values, dtype=np.intc)


@cache
def _dgelsd_function() -> Callable[..., None]:
    """Return LAPACK's dgelsd in SciPy's OpenBLAS, declared to take its 14 arguments as addresses: passed as
    integers, they skip numpy's per-argument ctypes conversion (a third of a small solve's cost)."""
    function = scipy_lapack_function("dgelsd")
    function.argtypes = [ctypes.c_void_p] * 14  # type: ignore[attr-defined]
    return function


def _dgelsd(*arguments: npt.NDArray[np.generic]) -> None:
    """Call LAPACK's dgelsd in SciPy's OpenBLAS with its 14 arguments, M, N, NRHS, A, LDA, B, LDB, S, RCOND,
    RANK, WORK, LWORK, IWORK, INFO, each an array: Fortran takes every argument by reference."""
    _dgelsd_function()(*(argument.ctypes.data for argument in arguments))


@cache
def _work_sizes(rows: int, columns: int, right_hand_sides: int, cond: float) -> tuple[int, int]:
    """Return the work sizes scipy's `lstsq` gives dgelsd for one problem shape: a workspace query (lwork -1),
    as `gelsd_lwork` makes it, read as `_compute_lwork` reads it (the float work size truncated)."""
    work, iwork, info = np.zeros(1), _ints(0), _ints(0)
    _dgelsd(
        *(_ints(rows), _ints(columns), _ints(right_hand_sides)),
        *(np.zeros(1), _ints(rows), np.zeros(1), _ints(max(rows, columns)), np.zeros(1)),
        *(np.array([cond]), _ints(0), work, _ints(-1), iwork, info),
    )
    if info[0] != 0:
        raise np.linalg.LinAlgError(f"dgelsd's workspace query failed ({info[0]})")
    return int(work[0]), int(iwork[0])


def _lstsq(lhs: FloatArray, rhs: FloatArray, cond: float) -> FloatArray:
    """Return `scipy.linalg.lstsq(lhs, rhs, cond=cond)[0]` for rhs (m,) or (m, k): scipy's own dgelsd call, with
    f2py's arguments (lhs copied to Fortran order, lda m; rhs copied into max(m, n) rows, zeros below a wide
    system's, ldb max(m, n)) and the same work sizes, without the checks that cost more than the solve."""
    rows, columns = lhs.shape
    right_hand_sides = rhs.shape[1] if rhs.ndim == 2 else 1
    padded = max(rows, columns)
    work_size, iwork_size = _work_sizes(rows, columns, right_hand_sides, cond)
    solution = np.zeros((padded, right_hand_sides), order="F")
    solution[:rows] = rhs.reshape(rows, right_hand_sides)
    info = _ints(0)
    _dgelsd(
        *(_ints(rows), _ints(columns), _ints(right_hand_sides)),
        *(np.array(lhs, dtype=np.float64, order="F"), _ints(rows), solution, _ints(padded)),
        *(np.empty(min(rows, columns)), np.array([cond]), _ints(0)),
        *(np.empty(work_size), _ints(work_size), np.empty(max(1, iwork_size), dtype=np.intc), info),
    )
    if info[0] != 0:
        raise np.linalg.LinAlgError(f"dgelsd failed ({info[0]})")
    return solution[:columns].reshape((columns, *rhs.shape[1:]))


def _pair_combination(weights: FloatArray) -> np.ufunc | None:
    """Return how ndimage's `NI_Correlate1D` combines the two samples of a pair of taps for correlation
    weights w: added where the weights, an odd number, are symmetric within DBL_EPSILON, subtracted where
    they are antisymmetric within it, and None (every tap on its own) otherwise."""
    size = weights.shape[0]
    if size % 2 == 0:
        return None
    half = size // 2
    outer, inner = weights[half + 1 :], weights[:half][::-1]  # w[half + i] and w[half - i], i = 1 .. half
    if not np.any(np.abs(outer - inner) > _EPS):
        return np.add
    if not np.any(np.abs(outer + inner) > _EPS):
        return np.subtract
    return None


def _convolve_inside(series: FloatArray, coefficients: FloatArray) -> FloatArray:
    """Return `scipy.ndimage.convolve1d(series, coefficients, axis=-1, mode="constant")` at the outputs that
    mode="interp" keeps, [L // 2, n - L // 2) of series (..., n) for L coefficients.

    convolve1d correlates with the coefficients reversed, w: output i reads x[i - (L - 1) // 2 + k] at tap k
    (an even L sits half a sample late), so the kept outputs read no padding. ndimage adds in one of two
    orders (`_pair_combination`): with pairs, from the centre tap's product, then (x[k] ± x[L - 1 - k]) * w[k]
    from the outermost pair inwards; without, from the last tap's product, then x[k] * w[k] from the first.
    numpy's elementwise operations round each product and each sum once, as ndimage's C loop (compiled
    without fused multiply-adds) does.
    """
    weights = coefficients[::-1]
    size = weights.shape[0]
    half = size // 2
    count = series.shape[-1] - 2 * half
    first = half - (size - 1) // 2  # the sample that tap 0 of the first kept output reads

    def tap(k: int) -> FloatArray:
        return series[..., first + k : first + k + count]

    combine = _pair_combination(weights)
    if combine is None:
        filtered = tap(size - 1) * weights[size - 1]
        for k in range(size - 1):
            filtered += tap(k) * weights[k]
    else:
        filtered = tap(half) * weights[half]
        for k in range(half):
            filtered += combine(tap(k), tap(size - 1 - k)) * weights[k]
    return filtered


@cache
def _coefficients(window: int, poly_order: int, deriv: int, delta: float) -> FloatArray:
    """Return the convolution coefficients (window,): scipy's `savgol_coeffs(use="conv")`."""
    half, remainder = divmod(window, 2)
    centre = half - 0.5 if remainder == 0 else half
    offsets = np.flip(np.arange(-centre, window - centre, dtype=np.float64))
    design = offsets ** np.arange(poly_order + 1, dtype=np.float64).reshape(-1, 1)
    target = np.zeros(poly_order + 1)
    target[deriv] = float(math.factorial(deriv)) / (delta**deriv)
    return _lstsq(design, target, _EPS * max(design.shape))  # a wide system, solved once per filter


def _polynomial_fit(samples: FloatArray, poly_order: int) -> FloatArray:
    """Return the least-squares polynomials (poly_order + 1, m) of columns (window, m) at 0, 1, ...: scipy's
    `_polyutils.polyfit` (a scaled Vandermonde matrix)."""
    positions = np.arange(0, samples.shape[0], dtype=np.float64)
    powers = np.flip(np.arange(poly_order + 1, dtype=np.float64))
    vandermonde = positions[:, None] ** powers[None, :]
    scale = np.sqrt(np.sum(vandermonde * vandermonde, axis=0))
    vandermonde /= scale
    fitted = _lstsq(vandermonde, samples, samples.shape[0] * _EPS)
    return (fitted.T / scale).T


def _derivative(polynomials: FloatArray, deriv: int) -> FloatArray:
    """Return the deriv-th derivative of polynomials (degree + 1, m), highest power first: scipy's `_polyder`."""
    if deriv == 0:
        return polynomials
    size = polynomials.shape[0]
    derived = np.array(polynomials[:-deriv], copy=True)
    for k in range(deriv):
        derived *= np.arange(size - k - 1, deriv - k - 1, -1, dtype=polynomials.dtype).reshape(-1, 1)
    return derived


def _evaluate(polynomials: FloatArray, at: FloatArray) -> FloatArray:
    """Return polynomials (degree + 1, m) at points (k, 1) by Horner's rule (k, m): scipy's `polyval`."""
    values = np.zeros_like(at)
    for coefficient in polynomials:
        values = values * at + coefficient
    return values


def _edges(num_steps: int, window: int) -> tuple[tuple[int, slice], tuple[int, slice]]:
    """Return (first sample of the fitted window, outputs it sets) at the start and at the end."""
    half = window // 2
    return (0, slice(0, half)), (num_steps - window, slice(num_steps - half, num_steps))


def _convolved(series: FloatArray, window: int, poly_order: int, deriv: int, delta: float) -> FloatArray:
    """Return series (..., n) with the outputs inside the edges filtered, by the convolution, and the edge
    outputs (`_edges`) still 0 for the caller to set."""
    half = window // 2
    filtered = np.zeros_like(series)
    coefficients = _coefficients(window, poly_order, deriv, delta)
    filtered[..., half : series.shape[-1] - half] = _convolve_inside(series, coefficients)
    return filtered


def savgol_filter(series: FloatArray, window: int, poly_order: int, deriv: int, delta: float) -> FloatArray:
    """Return scipy's `savgol_filter(series, window, poly_order, deriv, delta, axis=-1)` of a group (g, n)."""
    filtered = _convolved(series, window, poly_order, deriv, delta)
    for start, fitted in _edges(series.shape[-1], window):
        polynomials = _polynomial_fit(series[:, start : start + window].T, poly_order)
        at = np.arange(fitted.start - start, fitted.stop - start, dtype=np.float64).reshape(-1, 1)
        filtered[:, fitted] = (_evaluate(_derivative(polynomials, deriv), at) / (delta**deriv)).T
    return filtered


@cache
def savgol_operator(num_steps: int, window: int, poly_order: int, deriv: int, delta: float) -> FloatArray:
    """Return M (n, n) such that the filter of a series x (n,) is x @ M: the filter of the identity."""
    return savgol_filter(np.eye(num_steps), window, poly_order, deriv, delta)


# How far the matrix's edge outputs may lie from a group fit's, in units of eps * sum |x_i M_ij|: the worst
# measured over random pairs and PDM-Closed's groups of 15 is 38 (benchmarks/comfort_rounding.py).
EDGE_ERROR_ULPS = 128


def filter_batch(
    series: FloatArray, window: int, poly_order: int, deriv: int, delta: float
) -> tuple[FloatArray, FloatArray]:
    """Return the filter of series (..., n), each on its own, and a bound (..., n) on how far each output may
    lie from scipy's filter of any group holding the series: 0 where the convolution sets it (the same call
    gives the same bits), and a multiple of the rounding error of the matrix product at the edges."""
    filtered = _convolved(series, window, poly_order, deriv, delta)
    error = np.zeros_like(filtered)
    operator = savgol_operator(series.shape[-1], window, poly_order, deriv, delta)
    for _, fitted in _edges(series.shape[-1], window):
        edge = operator[:, fitted]
        filtered[..., fitted] = series @ edge
        error[..., fitted] = EDGE_ERROR_ULPS * _EPS * (np.abs(series) @ np.abs(edge))
    return filtered, error
