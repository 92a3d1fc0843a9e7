"""numpy's `exp` as it computes it on AVX-512 machines (Intel SVML's `__svml_exp8_ha`), on every host.

The two-stage weights are Gaussians exp(-d^2 / 0.2) of the start-point distances (`two_stage.weights`). On
AVX-512 CPUs numpy (2.x) runs SVML's exp, elsewhere the C library's; they differ in the last bit for a few
percent of arguments. The official results come from AVX-512 machines, so `exp_avx512` gives SVML's bits:
numpy's own where numpy runs SVML, this replay elsewhere (docs/engine.md, "Host dependence and kernels").

The replay is SVML's operations one by one, so it is exact by construction: each an IEEE operation on doubles
defined bit for bit, each FMA emulated exactly (`geometry._fused_multiply_add`), the one rounded toward zero
by `scorer.directed_rounding`, and `vscalefpd` by `ldexp` (exact: the results are normal). It gives this
host's SVML bits on every one of millions of random arguments (tests/test_svml_exp.py).

- Main path, |x| < 707.70...: x / ln 2 = k + f with k a multiple of 1/16 (rounded toward zero by the 1.5 * 2^48
  shifter), exp x = 2^floor(k) 2^(j/16) e^r, r = x - k ln 2 in two parts, e^r - 1 a polynomial, 2^(j/16)
  from a table as high (1 + low).
- SVML's scalar path (`__svml_dexp_ha_cout_rare_internal`) for 707.70... <= |x| up to the overflow and
  underflow thresholds: the same idea in plain SSE2 operations, rounded to nearest one by one, with k a
  multiple of 1/64 and a 64-entry table; results below 2^-1022 (x < -708.39...) are formed 2^60 larger and
  scaled down, as double-double where they stay normal enough. The Gaussians of the two-stage weights take
  it for start points 11.9 m or more from the endpoint (d^2 / 0.2 > 707.7).
Beyond those thresholds, and for infinite and NaN arguments, numpy's own value (0, inf, NaN) is SVML's.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from scorer.directed_rounding import fused_multiply_add_toward_zero
from scorer.geometry import FloatArray, _fused_multiply_add


def hex_table(*values: str) -> FloatArray:
    """Return the doubles written in C99 hex notation (SVML's tables, bit for bit)."""
    return np.array([float.fromhex(value) for value in values])


# 2^(i/64) = high (1 + low) (`_imldExpHATab`); every fourth entry is the main path's (and pow's) 2^(j/16).
EXP2_64THS_HI = hex_table(
    "0x1.0000000000000p+0", "0x1.02c9a3e778061p+0", "0x1.059b0d3158574p+0", "0x1.0874518759bc8p+0",
    "0x1.0b5586cf9890fp+0", "0x1.0e3ec32d3d1a2p+0", "0x1.11301d0125b51p+0", "0x1.1429aaea92de0p+0",
    "0x1.172b83c7d517bp+0", "0x1.1a35beb6fcb75p+0", "0x1.1d4873168b9aap+0", "0x1.2063b88628cd6p+0",
    "0x1.2387a6e756238p+0", "0x1.26b4565e27cddp+0", "0x1.29e9df51fdee1p+0", "0x1.2d285a6e4030bp+0",
    "0x1.306fe0a31b715p+0", "0x1.33c08b26416ffp+0", "0x1.371a7373aa9cbp+0", "0x1.3a7db34e59ff7p+0",
    "0x1.3dea64c123422p+0", "0x1.4160a21f72e2ap+0", "0x1.44e086061892dp+0", "0x1.486a2b5c13cd0p+0",
    "0x1.4bfdad5362a27p+0", "0x1.4f9b2769d2ca7p+0", "0x1.5342b569d4f82p+0", "0x1.56f4736b527dap+0",
    "0x1.5ab07dd485429p+0", "0x1.5e76f15ad2148p+0", "0x1.6247eb03a5585p+0", "0x1.6623882552225p+0",
    "0x1.6a09e667f3bcdp+0", "0x1.6dfb23c651a2fp+0", "0x1.71f75e8ec5f74p+0", "0x1.75feb564267c9p+0",
    "0x1.7a11473eb0187p+0", "0x1.7e2f336cf4e62p+0", "0x1.82589994cce13p+0", "0x1.868d99b4492edp+0",
    "0x1.8ace5422aa0dbp+0", "0x1.8f1ae99157736p+0", "0x1.93737b0cdc5e5p+0", "0x1.97d829fde4e50p+0",
    "0x1.9c49182a3f090p+0", "0x1.a0c667b5de565p+0", "0x1.a5503b23e255dp+0", "0x1.a9e6b5579fdbfp+0",
    "0x1.ae89f995ad3adp+0", "0x1.b33a2b84f15fbp+0", "0x1.b7f76f2fb5e47p+0", "0x1.bcc1e904bc1d2p+0",
    "0x1.c199bdd85529cp+0", "0x1.c67f12e57d14bp+0", "0x1.cb720dcef9069p+0", "0x1.d072d4a07897cp+0",
    "0x1.d5818dcfba487p+0", "0x1.da9e603db3285p+0", "0x1.dfc97337b9b5fp+0", "0x1.e502ee78b3ff6p+0",
    "0x1.ea4afa2a490dap+0", "0x1.efa1bee615a27p+0", "0x1.f50765b6e4540p+0", "0x1.fa7c1819e90d8p+0",
)  # fmt: skip
EXP2_64THS_LO = hex_table(
    "0x0.0p+0", "-0x1.160139cd8dc5dp-56", "0x1.cd2523567f613p-55", "0x1.0f74e61e6c861p-57",
    "0x1.79aa65d837b6dp-54", "0x1.ebe3d702f9cd1p-60", "-0x1.556522a2fbd0ep-54", "-0x1.1c923b9d5f416p-54",
    "-0x1.01b15eaa59348p-55", "0x1.b898c3f1353bfp-55", "0x1.aecf73e3a2f60p-54", "0x1.a6f4144a6c38dp-55",
    "0x1.68efde3a8a894p-54", "0x1.0472b981fe7f2p-55", "0x1.2f7e16d09ab31p-55", "0x1.b3782720c0ab4p-55",
    "0x1.34d754db0abb6p-55", "0x1.fdd395dd3f84ap-55", "-0x1.24aedcc4b5068p-54", "-0x1.1d1e83e9436d2p-56",
    "0x1.59f48a72a4c6dp-55", "-0x1.8a78f4817895bp-58", "0x1.363ed60c2ac11p-59", "0x1.ecce1daa10379p-57",
    "0x1.690cebb7aafb0p-56", "-0x1.f94340071a38ep-55", "-0x1.8dec6bd0f385fp-56", "0x1.3350518fdd78ep-54",
    "0x1.063e1e21c5409p-54", "0x1.432e62b64c035p-54", "-0x1.c33c53bef4da8p-55", "-0x1.3cedd78565858p-54",
    "-0x1.3b3efbf5e2228p-54", "-0x1.367efb86da9eep-57", "-0x1.81f647e5a3ecfp-56", "-0x1.619321e55e68ap-55",
    "-0x1.b32dcb94da51dp-56", "0x1.5ebe1abd66c55p-57", "-0x1.369b6f13b3734p-54", "-0x1.4d450d872576ep-54",
    "0x1.db72fc1f0eab4p-55", "0x1.bf68359f35f44p-56", "-0x1.da9b88b6c1e29p-58", "-0x1.2434322f4f9aap-54",
    "0x1.1affc2b91ce27p-56", "-0x1.7c50422622263p-55", "-0x1.1bbd1d3bcbb15p-54", "0x1.469846e735ab3p-55",
    "0x1.c1a7792cb3387p-55", "-0x1.5c3d956dcaebap-58", "-0x1.8d6f438ad9334p-57", "0x1.4ffd70a5fddcdp-56",
    "0x1.36eae30af0cb3p-56", "0x1.4e08fd10959acp-55", "0x1.76b2c6c921968p-57", "-0x1.fad5d3ffffa6fp-55",
    "0x1.4a385a63d07a7p-56", "0x1.e5a50d5c192acp-55", "-0x1.2d52107b43e1fp-55", "0x1.4b604603a88d3p-56",
    "-0x1.ff7128fd391f0p-55", "0x1.ec3bc41aa2008p-55", "0x1.a64a931d185eep-55", "0x1.7893b4d91cd9dp-56",
)  # fmt: skip
EXP2_16THS_HI, EXP2_16THS_LO = EXP2_64THS_HI[::4], EXP2_64THS_LO[::4]
# x / ln 2 + this, rounded toward zero (exp) or downward (pow): 1.5 * 2^48 (ulp 1/16) plus the exponent bias
# 1023, so the sum's low 4 bits are j and the bits above them floor(k) + 1023.
SIXTEENTHS_SHIFTER = float.fromhex("0x1.8000000003ff0p+48")

_h = float.fromhex
# Main path (`__svml_dexp_ha_data_internal_avx512`).
_MAIN_PATH_BOUND = _h("0x1.61da04cbafe44p+9")  # |x| from it: the scalar path
_INV_LN2 = _h("0x1.71547652b82fep+0")
_LN2_HI, _LN2_LO = _h("0x1.62e42fefa39efp-1"), _h("0x1.abc9e3b39803fp-56")
# e^r - 1 = r (c1 + r (c2 + ...)): pairs a r + b, highest first.
_MAIN_PAIRS = tuple(
    (_h(a), _h(b))
    for a, b in (
        ("0x1.7411836940c04p-10", "0x1.1101cbbc265c0p-7"),
        ("0x1.55557242d68fep-5", "0x1.5555553939732p-3"),
        ("0x1.000000000d008p-1", "0x1.fffffffffff70p-1"),
    )
)
# Scalar path (`_imldExpHATab`).
_SCALAR_LOW, _SCALAR_HIGH = _h("-0x1.74910d52d3051p+9"), _h("0x1.62e42fefa39efp+9")  # 0 below, inf above
_SUBNORMAL_BELOW = _h("-0x1.6232bdd7abcd2p+9")
_SIXTY_FOUR_OVER_LN2 = _h("0x1.71547652b82fep+6")
_INTEGER_SHIFTER = _h("0x1.8p+52")
_LN2_64THS_HI, _LN2_64THS_LO = _h("0x1.62e42fefa0000p-7"), _h("0x1.cf79abc9e3b3ap-46")
_SCALAR_COEFFICIENTS = tuple(  # e^r - 1 - r = r^2 (1/2 + r (1/6 + ...)), highest first
    _h(c)
    for c in (
        "0x1.6c16a1c2a3ffdp-10",
        "0x1.111123aaf20d3p-7",
        "0x1.5555555558fccp-5",
        "0x1.55555555548f8p-3",
        "0x1.0000000000000p-1",
    )
)
_SPLITTER = _h("0x1.8p+32")
_EXPONENT_BIAS = 0x3FF


def _power_of_two(biased_exponent: npt.NDArray[np.int64]) -> FloatArray:
    """Return the double with this (11-bit) exponent field and a zero significand."""
    return (biased_exponent << 52).view(np.float64)


def _main_path(x: FloatArray) -> FloatArray:
    fma = _fused_multiply_add
    shifted = fused_multiply_add_toward_zero(
        x, np.full_like(x, _INV_LN2), np.full_like(x, SIXTEENTHS_SHIFTER)
    )
    k = shifted - SIXTEENTHS_SHIFTER
    j = shifted.view(np.int64) & 15
    r = fma(-k, np.full_like(x, _LN2_HI), x)
    r = fma(-np.full_like(x, _LN2_LO), k, r)
    r2 = r * r
    first, second, third = (fma(r, np.full_like(x, a), np.full_like(x, b)) for a, b in _MAIN_PAIRS)
    polynomial = fma(r, fma(r2, fma(r2, first, second), third), EXP2_16THS_LO[j])
    return np.ldexp(fma(EXP2_16THS_HI[j], polynomial, EXP2_16THS_HI[j]), np.floor(k).astype(np.int64))


def _scalar_path(x: FloatArray) -> FloatArray:
    shifted = x * _SIXTY_FOUR_OVER_LN2 + _INTEGER_SHIFTER
    count = shifted - _INTEGER_SHIFTER  # N = round(64 x / ln 2)
    word = shifted.view(np.int64) & 0xFFFFFFFF  # N as a 32-bit word
    i, k = word & 63, word >> 6  # k's low 11 bits are floor(N / 64)'s
    r = (x - count * _LN2_64THS_HI) - count * _LN2_64THS_LO
    polynomial = r * _SCALAR_COEFFICIENTS[0] + _SCALAR_COEFFICIENTS[1]
    for coefficient in _SCALAR_COEFFICIENTS[2:]:
        polynomial = polynomial * r + coefficient
    tail = ((polynomial * r) * r + r + EXP2_64THS_LO[i]) * EXP2_64THS_HI[i]  # 2^(i/64) e^r - high
    biased = (k + _EXPONENT_BIAS) & 0x7FF
    with np.errstate(over="ignore"):
        normal = np.where(
            biased > 0x7FE,
            (tail + EXP2_64THS_HI[i]) * _power_of_two((biased - 1) & 0x7FF) * 2.0,
            (tail + EXP2_64THS_HI[i]) * _power_of_two(biased),
        )
    # Below 2^-1022: formed 2^60 larger, then scaled down in one rounding or as a split double-double.
    scaled_exponent = (k + _EXPONENT_BIAS + 60) & 0x7FF
    scale = _power_of_two(scaled_exponent)
    scaled_tail, scaled_high = tail * scale, scale * EXP2_64THS_HI[i]
    total = scaled_high + scaled_tail
    low = (scaled_high - total) + scaled_tail
    split = total * _SPLITTER
    head = (total + split) - split
    rest = low + (total - head)
    tiny = np.where(scaled_exponent <= 50, total * 2.0**-60, head * 2.0**-60 + rest * 2.0**-60)
    return np.where(x < _SUBNORMAL_BELOW, tiny, normal)


def svml_exp_emulated(argument: npt.ArrayLike) -> FloatArray:
    """Return np.exp(argument) as numpy computes it on AVX-512 machines, from float64 operations only."""
    x = np.asarray(argument, dtype=np.float64)
    main = np.abs(x) < _MAIN_PATH_BOUND
    scalar = ~main & (x >= _SCALAR_LOW) & (x <= _SCALAR_HIGH)
    with np.errstate(over="ignore", under="ignore"):
        return np.where(
            main,
            _main_path(np.where(main, x, 0.0)),
            np.where(scalar, _scalar_path(np.where(scalar, x, -708.0)), np.exp(x)),
        )


# Arguments where SVML's exp rounds other than the C library, with SVML's results: numpy is SVML here exactly
# when it gives these.
_SVML_PROBE_ARGUMENTS = np.array([-18.263, -9.603, -19.534, -1.586])
_SVML_PROBE_EXP = hex_table(
    "0x1.9247fc031c235p-27", "0x1.1b39559eb696ep-14", "0x1.c37102b907772p-29", "0x1.a3504545d82ecp-3"
)
NUMPY_EXP_IS_SVML = bool(np.array_equal(np.exp(_SVML_PROBE_ARGUMENTS), _SVML_PROBE_EXP))


def exp_avx512(argument: npt.ArrayLike) -> FloatArray:
    """Return np.exp(argument) as the devkit computed it on the AVX-512 machines of the official results:
    numpy's own where numpy runs SVML (exact, and faster), the replay elsewhere."""
    if NUMPY_EXP_IS_SVML:
        return np.exp(argument)
    return svml_exp_emulated(argument)
