"""numpy's `power` as it computes it on AVX-512 machines (Intel SVML's `__svml_pow8_ha`), on every host.

PDM-Closed's IDM takes (v / v0) ** 10 every step (`pdm_closed.idm_step`). On AVX-512 CPUs numpy (2.x) runs
SVML's pow, elsewhere the C library's, and the two differ by an ulp on about 5 % of the IDM's bases: SVML's is
not correctly rounded (5 % of x ** 10 for x in [0, 2] differ from the correctly rounded value), so no
correctly rounded computation can stand for it, and the C library's nearly is one. The official results come
from AVX-512 machines, so `power_avx512` gives SVML's bits: numpy's own where numpy runs SVML, this replay
elsewhere (docs/engine.md, "Host dependence and kernels").

The replay is SVML's main path operation for operation, so it is exact by construction, not by tuning:
every operation is an IEEE operation on doubles whose result is defined bit for bit, each FMA emulated exactly
(`geometry._fused_multiply_add`), the roundings toward zero and downward that SVML asks of a few operations
emulated exactly (`scorer.directed_rounding`), `vrcp14pd` from its table (`scorer.rcp14`), and `vgetmantpd`,
`vgetexppd`, `vrndscalepd` and `vreducepd`, which are exact, by `frexp`, `round` and `floor` (vreducepd's
final subtraction rounds downward). The tables and coefficients are SVML's (`__svml_dpow_ha_data_internal_avx512`;
2^(j/16) and the shifter are exp's, `scorer.svml_exp`).
It gives this host's SVML bits on every one of millions of random bases (tests/test_svml_pow.py).

log2 x = e + log2 m for x = m 2^e, m in [1/2, 1): m times r (`vrcp14pd`'s estimate of 1/m rounded to 1/32)
is near 1, log2 m = log2(m r) - log2 r with -log2 r (or 1 - log2 r, e one less) from a 32-entry table; log2(m r)
= log2(1 + 2u), u = (m r - 1) / 2, a polynomial whose first two terms are kept in double-double. y log2 x
(= W) is formed in double-double rounded toward zero, then 2^W = 2^n 2^(j/16) 2^f with 2^(j/16) from a
16-entry table and 2^f a polynomial.

The main path covers positive finite bases with |W| <= 1020 (for the exponent 10: 2^-102 <= x <= 2^102).
Elsewhere (zero, negative, infinite or NaN bases, results near the underflow or the overflow threshold)
SVML takes a scalar path of its own, which this module does not replay: numpy's own value is returned there.
It equals SVML's for zero, infinite and NaN bases; for negative ones SVML's differs from the C library's on
about 0.1 % of bases. The IDM's bases are negative only if the ego's speed is: none on the reference and
knife-edge scenes (docs/engine.md lists it with the host-dependent functions).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from scorer.directed_rounding import (
    add_downward,
    add_toward_zero,
    fused_multiply_add_toward_zero,
    multiply_toward_zero,
)
from scorer.geometry import FloatArray, _fused_multiply_add
from scorer.rcp14 import rcp14
from scorer.svml_exp import EXP2_16THS_HI, EXP2_16THS_LO, SIXTEENTHS_SHIFTER, hex_table

# -log2 r as high (22-34 bits) + low part, for r = 1 + i/32 (i = 0 .. 15, e stays) and, for r in [1.5, 2),
# 1 - log2 r (i = 16 .. 31, e one less); r = 2 takes entry 0.
_LOG_HI = hex_table(
    "0x0.0p+0", "-0x1.6bad3758e0000p-5", "-0x1.663f6fac90000p-4", "-0x1.08c588cda8000p-3",
    "-0x1.5c01a39fc0000p-3", "-0x1.acf5e2db50000p-3", "-0x1.fbc16b9028000p-3", "-0x1.24407ab0e0000p-2",
    "-0x1.49a784bcd0000p-2", "-0x1.6e221cd9d0000p-2", "-0x1.91bba891f0000p-2", "-0x1.b47ebf7388000p-2",
    "-0x1.d6753e0330000p-2", "-0x1.f7a8568cb0000p-2", "-0x1.0c10500d64000p-1", "-0x1.1bf311e95e000p-1",
    "0x1.a8ff971810000p-2", "0x1.8a8980abfc000p-2", "0x1.6cb0f6865c000p-2", "0x1.4f6fbb2cec000p-2",
    "0x1.32bfee3710000p-2", "0x1.169c053640000p-2", "0x1.f5fd8a9060000p-3", "0x1.bfc67a8000000p-3",
    "0x1.8a8980abf8000p-3", "0x1.563dc29ff8000p-3", "0x1.22dadc2ab0000p-3", "0x1.e0b1ae8f30000p-4",
    "0x1.7d60496d00000p-4", "0x1.1bb32a6000000p-4", "0x1.77394c9da0000p-5", "0x1.743ee86200000p-6",
)  # fmt: skip
_LOG_LO = hex_table(
    "0x0.0p+0", "-0x1.fb0e626c0de13p-42", "-0x1.3167ccc538261p-44", "0x1.871a7610e40bdp-45",
    "0x1.4bc302ffa76fbp-42", "0x1.36c101ee13440p-43", "0x1.7f5dc57266758p-43", "-0x1.ce60916e52e91p-44",
    "-0x1.b8afe492bf6ffp-42", "-0x1.9bcaf1aa4168ap-43", "-0x1.708b4b2b5056cp-42", "-0x1.50520a377c7ecp-45",
    "0x1.5f101c141e670p-42", "-0x1.b3b3864c60011p-44", "0x1.5669df6a2b592p-43", "0x1.fe43895d8ac46p-42",
    "0x1.4bc302ffa76fbp-43", "-0x1.66cccab240e90p-45", "0x1.1d406db502403p-43", "0x1.661e393a16b95p-44",
    "-0x1.1979a5db68722p-42", "-0x1.d4f1b95e0ff45p-43", "0x1.f1a4847f7b278p-42", "-0x1.667f21fa8423fp-44",
    "0x1.e9933354dbf17p-42", "0x1.6590643906f2ap-42", "0x1.a4b69691d7994p-42", "-0x1.54cda62d3926ep-47",
    "-0x1.12ce6312ebb82p-42", "0x1.52743318a8a57p-42", "-0x1.4e55443478fe0p-42", "-0x1.95539356f93dcp-43",
)  # fmt: skip
_TWO_OVER_LN2 = float.fromhex("0x1.71547652b82fep+1")  # log2(1 + 2u) = (2 / ln 2)(u - u^2 + ...)
# The rest of log2(1 + 2u) as pairs (a, b) = a u + b, highest first, combined in SVML's order (below); the
# last pair is the low parts of the first two terms.
_LOG_PAIRS = tuple(
    (float.fromhex(a), float.fromhex(b))
    for a, b in (
        ("-0x1.27a394386376fp+7", "0x1.4873cf87141d1p+6"),
        ("-0x1.715473528efc1p+5", "0x1.a617607e55815p+4"),
        ("-0x1.ec709dc3b71a1p+3", "0x1.2776c50effbdep+3"),
        ("-0x1.71547652b82fcp+2", "0x1.ec709dc3a03fdp+1"),
        ("-0x1.778d9c7190437p-55", "0x1.777df70b75d10p-55"),
    )
)
# 2^f - 1 over f as pairs a f + b, highest first.
_EXP2_PAIRS = tuple(
    (float.fromhex(a), float.fromhex(b))
    for a, b in (
        ("0x1.4a1d7f58c2d59p-13", "0x1.5d7472783d279p-10"),
        ("0x1.3b2ad1b14ebaap-7", "0x1.c6b08d4ad8eb9p-5"),
        ("0x1.ebfbdff84554dp-3", "0x1.62e42fefa398bp-1"),
    )
)
_MAIN_PATH_W = 1020.0  # |W| above it: SVML's scalar path
_EXPONENT_MASK = 0x7FF0000000000000


def svml_power_emulated(base: npt.ArrayLike, exponent: float) -> FloatArray:
    """Return np.power(base, exponent) as numpy computes it on AVX-512 machines, from float64 operations only.

    `__svml_pow8_ha`'s main path in its order of operations; numpy's own value off it (module docstring)."""
    x = np.asarray(base, dtype=np.float64)
    fma = _fused_multiply_add
    positive = (x > 0) & np.isfinite(x)
    x_in = np.where(positive, x, 1.0)
    y = np.full_like(x_in, exponent)

    def pair(a: float, b: float, t: FloatArray) -> FloatArray:
        return fma(t, np.full_like(t, a), np.full_like(t, b))

    # log2 x, as high + low.
    mantissa, exponent_plus_one = np.frexp(x_in)  # vgetmantpd [1/2, 1), vgetexppd + 1
    r = np.round(rcp14(mantissa) * 32) / 32
    e = np.where(r < 1.5, exponent_plus_one, exponent_plus_one - 1).astype(np.float64)
    index = (r.view(np.int64) >> 47) & 31  # r's top 5 fraction bits (r = 2 gives 0)
    u = fma(mantissa * 0.5, r, np.full_like(x_in, -0.5))
    u2 = u * u
    first, second, third, fourth, fifth = (pair(a, b, u) for a, b in _LOG_PAIRS)
    low = fma(u2 * u2, fma(u2, first, second), fma(u2, third, fourth))
    low = fma(u, fma(u2, low, fifth), _LOG_LO[index])
    table_and_exponent = _LOG_HI[index] + e
    linear = np.full_like(x_in, _TWO_OVER_LN2)
    head = fma(linear, u, table_and_exponent)  # e + T + (2 / ln 2) u
    term = head - table_and_exponent
    high = fma(-u, term, head)  # minus the square term
    term_error = fma(u, linear, -term)
    square_error = fma(term, u, -(head - high))
    log_low = low + (fma(-term_error, u, term_error) - square_error)
    log_high = high + log_low
    log_low = log_low - (log_high - high)
    # W = y log2 x, rounded toward zero, as product + its low part.
    product = multiply_toward_zero(log_high, y)
    product_low = fused_multiply_add_toward_zero(y, log_low, fma(y, log_high, -product))
    w = add_toward_zero(product, product_low)
    shifted = add_downward(w, np.full_like(x_in, SIXTEENTHS_SHIFTER))
    f = add_downward(w, -np.floor(w * 16) / 16) + (
        product_low - (w - product)
    )  # vreducepd, then W's low part
    # 2^W = 2^n 2^(j/16) 2^f.
    bits = shifted.view(np.int64)
    j = bits & 15
    scale = ((bits << 48) & _EXPONENT_MASK).view(np.float64)
    f2 = f * f
    first, second, third = (pair(a, b, f) for a, b in _EXP2_PAIRS)
    polynomial = fma(f, fma(f2, fma(f2, first, second), third), EXP2_16THS_LO[j])
    with np.errstate(over="ignore"):  # lanes off the main path only
        result = fma(EXP2_16THS_HI[j], polynomial, EXP2_16THS_HI[j]) * scale
    main_path = positive & (np.abs(w) <= _MAIN_PATH_W)
    return np.where(main_path, result, np.power(x, exponent))


# Bases whose tenth power SVML rounds other than the C library, with SVML's results: numpy is SVML here exactly
# when it gives these.
_SVML_PROBE_BASES = np.array([0.7771, 1.4142, 1.0106, 2.8012])
_SVML_PROBE_POWERS = hex_table(
    "0x1.48f308d97fb93p-4", "0x1.fff36e40df3c4p+4", "0x1.1c77b8bcf1314p+0", "0x1.d0cb73f450cb1p+14"
)
NUMPY_POWER_IS_SVML = bool(np.array_equal(np.power(_SVML_PROBE_BASES, 10.0), _SVML_PROBE_POWERS))


def power_avx512(base: npt.ArrayLike, exponent: float) -> FloatArray:
    """Return np.power(base, exponent) as the devkit computed it on the AVX-512 machines of the official
    results: numpy's own where numpy runs SVML (exact, and faster), the replay elsewhere."""
    if NUMPY_POWER_IS_SVML:
        return np.power(base, exponent)
    return svml_power_emulated(base, exponent)
