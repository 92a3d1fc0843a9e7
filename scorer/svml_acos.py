"""numpy's `arccos` as it computes it on AVX-512 machines (Intel SVML's `__svml_acos8_ha`), on every host.

NC's rear-collision test and TTC's ahead test take the arccos of a target's direction against the ego heading
(`metrics.contacts`) and compare it with bounds. On AVX-512 CPUs numpy (2.x) runs SVML's arccos, elsewhere the
C library's, and the two differ in the last bit for some arguments: only an angle within an ulp of a bound
could move a result, but the official results come from AVX-512 machines, so `arccos_avx512` gives SVML's
bits: numpy's own where numpy runs SVML, this replay elsewhere (docs/engine.md, "Host dependence and kernels").

The replay is SVML's operations one by one, so it is exact by construction: each an IEEE operation on doubles
defined bit for bit, each FMA emulated exactly (`geometry._fused_multiply_add`), `vrsqrt14pd` from its table
(`scorer.rsqrt14`). It gives this host's SVML bits on every one of millions of random arguments
(tests/test_svml_acos.py). With z = min(x^2, (1 - |x|) / 2):
- |x| < 1/2: acos x = pi/2 - (x + x z P(z)), pi/2 as high + low part;
- |x| >= 1/2: acos |x| = 2 asin(sqrt(Y)), Y = (1 - |x|) / 2, with 2 sqrt(Y) from `vrsqrt14pd`'s estimate R as
  2Y R, corrected by a polynomial in e = 2(Y R^2 - 1) and the product's exact error; pi minus it for x < 0.
Arguments beyond [-1, 1] and NaN take SVML's special path: numpy's own value (NaN) is returned there.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from scorer.geometry import FloatArray, _fused_multiply_add
from scorer.rsqrt14 import rsqrt14
from scorer.svml_exp import hex_table

# `__svml_dacos_ha_data_internal`.
_TINY = float.fromhex("0x1.0p-255")  # Y below it: the estimate is taken as 0
# 2 sqrt(Y) (1 + e (c1 + e (c2 + ...))) corrects the estimate: pairs highest first.
_SQRT_COEFFICIENTS = hex_table(
    "-0x1.18000993b24c3p-6", "0x1.400006f70d42dp-5", "-0x1.7fffffffffe97p-4", "0x1.fffffffffff9dp-3"
)
# asin(s) = s + s z P(z): P's coefficients as pairs a z + b, highest first, combined in SVML's order (below).
_ASIN_PAIRS = tuple(
    (float.fromhex(a), float.fromhex(b))
    for a, b in (
        ("0x1.07520c70eb909p-5", "-0x1.0fb17f7dbb0edp-6"),
        ("0x1.43f44bfbc3baep-6", "0x1.a583395d45ed5p-8"),
        ("0x1.8f8dc2afccad6p-7", "0x1.c6dbbcb88bd57p-7"),
        ("0x1.1c6dcf538ad2ep-6", "0x1.6e89cebdefaddp-6"),
        ("0x1.f1c72e13ad8bep-6", "0x1.6db6db3b445f8p-5"),
    )
)
_ASIN_LAST = hex_table("0x1.333333337e0dep-4", "0x1.555555555529cp-3")
_PI_HI, _PI_LO = float.fromhex("0x1.921fb54442d18p+1"), float.fromhex("0x1.1a62633145c07p-53")
_HALF_PI_HI, _HALF_PI_LO = float.fromhex("0x1.921fb54442d18p+0"), float.fromhex("0x1.1a62633145c07p-54")


def svml_arccos_emulated(argument: npt.ArrayLike) -> FloatArray:
    """Return np.arccos(argument) as numpy computes it on AVX-512 machines, from float64 operations only.

    `__svml_acos8_ha`'s main path in its order of operations; numpy's own value off it (module docstring)."""
    x = np.asarray(argument, dtype=np.float64)
    fma = _fused_multiply_add
    main_path = np.abs(x) <= 1.0
    x_in = np.where(main_path, x, 0.0)
    negative = np.signbit(x_in)
    minus_abs = -np.abs(x_in)
    y = fma(minus_abs, np.full_like(x_in, 0.5), np.full_like(x_in, 0.5))  # (1 - |x|) / 2
    square = minus_abs * minus_abs
    estimate = np.where(y < _TINY, 0.0, rsqrt14(np.where(y < _TINY, 1.0, y)))
    z = np.where(square < y, square, y)
    root_branch = ~(z < y)  # |x| >= 1/2
    beyond_x = ~(z < x_in)  # with root_branch: x < 0
    twice_y = y + y
    root = twice_y * estimate  # about 2 sqrt(Y)
    e = fma(estimate * estimate, twice_y, np.full_like(x_in, -2.0))
    root_error = fma(estimate, twice_y, -root)
    correction = fma(e, np.full_like(x_in, _SQRT_COEFFICIENTS[0]), np.full_like(x_in, _SQRT_COEFFICIENTS[1]))
    for coefficient in _SQRT_COEFFICIENTS[2:]:
        correction = fma(e, correction, np.full_like(x_in, coefficient))
    correction = fma(root * e, correction, -root_error)  # 2 sqrt(Y) = root - correction
    first, second, third, fourth, fifth = (
        fma(z, np.full_like(x_in, a), np.full_like(x_in, b)) for a, b in _ASIN_PAIRS
    )
    z2 = z * z
    polynomial = fma(z2 * z2, fma(z2, first, second), fma(z2, third, fourth))
    polynomial = fma(z2, polynomial, fifth)
    correction = np.where(root_branch, correction, 0.0)
    for coefficient in _ASIN_LAST:
        polynomial = fma(z, polynomial, np.full_like(x_in, coefficient))
    polynomial = polynomial * z
    # acos x = high + (-1)^negative (low + s + s z P(z)), s = -|x| or 2 sqrt(Y), with pi/2, pi or 0 as high + low.
    reflected = root_branch & beyond_x
    high = np.where(reflected, _PI_HI, np.where(root_branch, 0.0, _HALF_PI_HI))
    low = np.where(reflected, _PI_LO, np.where(root_branch, 0.0, _HALF_PI_LO))
    low = np.where(negative, -low, low)
    s = np.where(root_branch, root, minus_abs)
    result = fma(s - correction, polynomial, low - correction) + s
    result = np.where(negative, -result, result) + high
    with np.errstate(invalid="ignore"):
        return np.where(main_path, result, np.arccos(x))


# Arguments where SVML's arccos rounds other than the C library, with SVML's results: numpy is SVML here
# exactly when it gives these.
_SVML_PROBE_ARGUMENTS = np.array([0.3924, -0.4037, 0.4443, 0.6995])
_SVML_PROBE_ARCCOS = hex_table(
    "0x1.2ae5025e0fca2p+0", "0x1.fc81ae60e0690p+0", "0x1.1c43689aeb0f4p+0", "0x1.979a40b539ba7p-1"
)
NUMPY_ARCCOS_IS_SVML = bool(np.array_equal(np.arccos(_SVML_PROBE_ARGUMENTS), _SVML_PROBE_ARCCOS))


def arccos_avx512(argument: npt.ArrayLike) -> FloatArray:
    """Return np.arccos(argument) as the devkit computed it on the AVX-512 machines of the official results:
    numpy's own where numpy runs SVML (exact, and faster), the replay elsewhere."""
    if NUMPY_ARCCOS_IS_SVML:
        return np.arccos(argument)
    return svml_arccos_emulated(argument)
