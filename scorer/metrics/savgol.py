"""Savitzky-Golay filters computed as scipy 1.17's `savgol_filter(mode="interp")` computes them.

The comfort metric filters every series with `scipy.signal.savgol_filter`. Its outputs come from two
computations: a convolution (`scipy.ndimage.convolve1d`, each series on its own) and, for the first and
last window // 2 outputs, polynomials fitted to the first or last `window` samples by one LAPACK
least-squares solve (`scipy.linalg.lstsq`) over every series of the call. That solve's last bits depend
on how many series share it, so only a call on the very same group of series reproduces the devkit's bits
there (docs/engine.md, "Comfort filters").

`savgol_filter` makes scipy's calls on a group, bit-identical to scipy (`tests/test_metrics_savgol.py`);
`filter_batch` filters any number of series at once: the convolution exactly, the edges through the
filter's matrix (the filter of the identity) with a bound on their distance from any group's fit. Both
avoid importing `scipy.signal`, which costs about 0.6 s more at start-up than `scipy.linalg` and
`scipy.ndimage` (docs/engine.md, "Start-up").
"""

from __future__ import annotations

import math
from functools import cache
from typing import Any

import numpy as np

from scorer.geometry import FloatArray

_EPS = float(np.finfo(np.float64).eps)


@cache
def _gelsd(rows: int, columns: int, right_hand_sides: int, cond: float) -> tuple[Any, int, int]:
    """Return LAPACK's dgelsd and the work sizes scipy's `lstsq` asks it for, for one problem shape."""
    from scipy.linalg.lapack import _compute_lwork, get_lapack_funcs

    probe = np.zeros((1, 1))
    gelsd, gelsd_lwork = get_lapack_funcs(("gelsd", "gelsd_lwork"), (probe, probe))
    lwork, iwork = _compute_lwork(gelsd_lwork, rows, columns, right_hand_sides, cond)
    return gelsd, lwork, iwork


def _lstsq(lhs: FloatArray, rhs: FloatArray, cond: float) -> FloatArray:
    """Return `scipy.linalg.lstsq(lhs, rhs, cond=cond)[0]` for a tall or square lhs: the same dgelsd call with
    the same work sizes, without the checks that cost more than the solve."""
    rows, columns = lhs.shape
    gelsd, lwork, iwork = _gelsd(rows, columns, rhs.shape[1] if rhs.ndim == 2 else 1, cond)
    solution, _, _, info = gelsd(lhs, rhs, lwork, iwork, cond, False, False)
    if info != 0:
        raise np.linalg.LinAlgError(f"dgelsd failed ({info})")
    return solution[:columns]


@cache
def _coefficients(window: int, poly_order: int, deriv: int, delta: float) -> FloatArray:
    """Return the convolution coefficients (window,): scipy's `savgol_coeffs(use="conv")`."""
    half, remainder = divmod(window, 2)
    centre = half - 0.5 if remainder == 0 else half
    offsets = np.flip(np.arange(-centre, window - centre, dtype=np.float64))
    design = offsets ** np.arange(poly_order + 1, dtype=np.float64).reshape(-1, 1)
    target = np.zeros(poly_order + 1)
    target[deriv] = float(math.factorial(deriv)) / (delta**deriv)
    from scipy.linalg import lstsq  # a wide system (scipy pads b), solved once per filter

    return lstsq(design, target, cond=_EPS * max(design.shape))[0]


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


def savgol_filter(series: FloatArray, window: int, poly_order: int, deriv: int, delta: float) -> FloatArray:
    """Return scipy's `savgol_filter(series, window, poly_order, deriv, delta, axis=-1)` of a group (g, n)."""
    from scipy.ndimage import convolve1d

    filtered = convolve1d(series, _coefficients(window, poly_order, deriv, delta), axis=-1, mode="constant")
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
    from scipy.ndimage import convolve1d

    coefficients = _coefficients(window, poly_order, deriv, delta)
    filtered = convolve1d(series, coefficients, axis=-1, mode="constant")
    error = np.zeros_like(filtered)
    operator = savgol_operator(series.shape[-1], window, poly_order, deriv, delta)
    for _, fitted in _edges(series.shape[-1], window):
        edge = operator[:, fitted]
        filtered[..., fitted] = series @ edge
        error[..., fitted] = EDGE_ERROR_ULPS * _EPS * (np.abs(series) @ np.abs(edge))
    return filtered, error
