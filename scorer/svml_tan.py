"""numpy's `tan` as it computes it on AVX-512 machines (Intel SVML's `__svml_tan8_ha`), on every host.

The bicycle model takes the tangent of the steering angle twice a step (docs/engine.md, "Simulation: the
bicycle model"). On AVX-512 CPUs numpy (2.x) runs SVML's tan, which is not correctly rounded: about 0.5 % of
angles in [-pi/3, pi/3] get one ulp more or less than from the C library numpy calls elsewhere (AVX2 and
baseline builds agree with it). The official results come from AVX-512 machines, so `tan_avx512` gives SVML's
bits: numpy's own where numpy runs SVML, this replay elsewhere (docs/engine.md, "Host dependence and kernels").

The replay is SVML's main path operation for operation, each FMA emulated (`geometry._fused_multiply_add`):
x = N pi/16 + r with r in three parts, tan r by an odd polynomial, then tan(N pi/16 + r) =
(T_N + tan r) / (1 - T_N tan r) with T_N from a 16-entry table, divided through `vrcp14pd`'s estimate
(`scorer.rcp14`) and one Newton step each for the reciprocal and the quotient. It gives this host's SVML bits
on every one of 9e6 random angles in [-1.4, 1.4] (with the correctly rounded reciprocal in place of the
estimate, 0.3 % would differ). Where exact products make an FMA one rounded sum (the reduction by N pi/16, the
estimate's residual) the replay forms it so, with about a third fewer numpy calls (the simulation takes a tan a
step; tests compare these with the emulated FMAs). It covers 2^-300 <= |x| < 1.4, where no operand meets the
table's entry for pi/2 (its FMAs would overflow the emulation) and none underflows; the steering angle is
clipped to pi/3. Elsewhere numpy's own value is returned (below 2^-300 tan x rounds to x on every path).

A few angles go through `_svml_tan_float`, the same replay on Python floats: the simulation takes one tan a
step of arrays as small as one angle (a one-token `navsim-lb score` makes 41 such calls), where the numpy
replay costs about 0.3 ms a call and the float replay about 0.012 ms an angle (tests check the bits).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from scorer.geometry import (
    FloatArray,
    IntArray,
    _estimate_residual,
    _fused_multiply_add,
    _fused_multiply_add_float,
    _veltkamp_split,
)
from scorer.rcp14 import rcp14, rcp14_float

# Constants of `__svml_tan8_ha` (table `__svml_dtan_ha_data_internal`): N = round(x * 16 / pi) by the
# 1.5 * 2^52 shifter, pi/16 in three parts, tan(j pi/16) = hi + lo for j = N mod 16, the polynomial in r^2.
_SIXTEEN_OVER_PI = float.fromhex("0x1.45f306dc9c883p+2")
_SHIFTER = float.fromhex("0x1.8p+52")
_PI16_PARTS = tuple(
    float.fromhex(h) for h in ("0x1.921fb54442d18p-3", "0x1.1a62633p-57", "0x1.45c06e0e68948p-89")
)
_TAN_HI_FIRST = [
    "0x0.0p+0",
    "0x1.975f5e0553158p-3",
    "0x1.a827999fcef32p-2",
    "0x1.561b82ab7f990p-1",
    "0x1.0p+0",
    "0x1.7f218e25a7461p+0",
    "0x1.3504f333f9de6p+1",
    "0x1.41bfee2424771p+2",
]
_TAN_LO_FIRST = [
    "0x0.0p+0",
    "0x1.ef5d367441946p-61",
    "0x1.08b2fb1366ea9p-56",
    "0x1.7a8c52172b675p-55",
    "0x0.0p+0",
    "0x1.419fa6954928fp-54",
    "0x1.21165f626cdd5p-53",
    "0x1.10706fed37f0ep-55",
]


def _odd_table(first_half: list[str], pole: float) -> FloatArray:
    """Return SVML's 16 entries: j = 0 .. 7 as given, j = 8 the pole, j = 9 .. 15 the negated mirror of 7 .. 1
    (tan((16 - j) pi/16) = -tan(j pi/16)); entry 0 is -0.0 as in SVML's table."""
    half = [float.fromhex(h) for h in first_half]
    return np.array([-0.0, *half[1:], pole, *(-value for value in reversed(half[1:]))])


_TAN_HI = _odd_table(_TAN_HI_FIRST, -float.fromhex("0x1.fffffffffffffp+1023"))
_TAN_LO = _odd_table(_TAN_LO_FIRST, -float.fromhex("0x1.0p+971"))
_TAN_POLYNOMIAL = tuple(  # highest coefficient first: r^2 ... r^10 of tan r = r + r^3 P(r^2)
    float.fromhex(h)
    for h in (
        "0x1.25cccc7c9fa5dp-7",
        "0x1.664ab664efba9p-6",
        "0x1.ba1ba489d25cap-5",
        "0x1.11111110b0802p-3",
        "0x1.55555555555dcp-2",
    )
)

# The replay's domain (module docstring): numpy's value below and above.
_REPLAY_LOW, _REPLAY_HIGH = 2.0**-300, 1.4


def _nearest_sixteenth(x: FloatArray) -> tuple[FloatArray, IntArray]:
    """Return N (as floats) and j = N mod 16 for angles |x| < 1.4, N = round(x 16/pi) as SVML forms it: the
    shifter 1.5 * 2^52 added to x 16/pi in an FMA, whose result is an integer (|x 16/pi| < 8) rounded from
    the exact product, ties to even. `rint` of the rounded product is that integer unless the product rounds
    onto a half-integer (rounding is monotone and half-integers are doubles), where the emulated FMA decides."""
    product = x * _SIXTEEN_OVER_PI
    count = np.rint(product) + 0.0  # SVML's N is the shifted value minus the shifter: 0, never -0
    tie = np.abs(product - count) == 0.5
    if tie.any():
        shifted = _fused_multiply_add(x, _SIXTEEN_OVER_PI, _SHIFTER, _SIXTEEN_OVER_PI_SPLIT)
        count = np.where(tie, shifted - _SHIFTER, count)
    return count, count.astype(np.int64) & 15


def _reduced_angle(x: FloatArray, count: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return r = x - N pi/16 as SVML's high and low parts, for |N| <= 7, its FMAs with -N and pi/16's three
    parts formed without emulation where exact products allow (the emulation otherwise):

    - N has at most 3 significant bits, part 1 50 and part 2 29, so N times either is exact and each FMA with
      them is one rounded sum;
    - |N part 3| < 2^-85, below half an ulp of any |value| >= 2^-30, so where the second reduction is that large
      (or N = 0) the third FMA returns it unchanged, and the low part's FMA with part 3 adds N part 3 to 0:
      the product rounded once.
    """
    minus_count = -count
    pi_1, pi_2, pi_3 = _PI16_PARTS
    first = x + minus_count * pi_1
    second = first + minus_count * pi_2
    low_first = (first - second) + minus_count * pi_2
    if np.all((np.abs(second) >= _PART_3_NEGLIGIBLE) | (count == 0)):
        return second, low_first - count * pi_3
    split_3 = _PI16_SPLITS[2][1]
    high = _fused_multiply_add(minus_count, pi_3, second, split_3)
    return high, low_first - _fused_multiply_add(count, pi_3, high - second, split_3)


# Reductions at least this large absorb N times pi/16's third part (`_reduced_angle`).
_PART_3_NEGLIGIBLE = 2.0**-30


def svml_tan_emulated(angle: npt.ArrayLike) -> FloatArray:
    """Return np.tan(angle) as numpy computes it on AVX-512 machines, from float64 operations only.

    `__svml_tan8_ha`'s main path in its order of operations (the register names of SVML's listing in the
    comments where the parts get their meaning)."""
    x = np.asarray(angle, dtype=np.float64)
    if x.size <= _FLOAT_REPLAY_MAX_ANGLES:
        values = [_svml_tan_float(value) for value in x.ravel().tolist()]
        return np.array(values, dtype=np.float64).reshape(x.shape)
    fma = _fused_multiply_add
    replayed = (np.abs(x) >= _REPLAY_LOW) & (np.abs(x) < _REPLAY_HIGH)
    x_in = np.where(replayed, x, 1.0)
    # Operands of several products are split once, constants' splits precomputed (`_exact_multiply_add`), and
    # the reduction's FMAs not emulated where exact products make them plain sums (`_nearest_sixteenth`,
    # `_reduced_angle`).
    count, index = _nearest_sixteenth(x_in)
    high, low = _reduced_angle(x_in, count)
    # tan r = high + (high r^2 P(r^2) + low), kept as value + its rounding error.
    square = high * high
    square_high, square_low = _veltkamp_split(square)
    polynomial = fma(
        square, _TAN_POLYNOMIAL[0], _TAN_POLYNOMIAL[1], _TAN_POLYNOMIAL_SPLIT, (square_high, square_low)
    )
    for coefficient in _TAN_POLYNOMIAL[2:]:
        polynomial = fma(square, polynomial, coefficient, None, (square_high, square_low))
    correction = fma(-square, polynomial * high, -low, None, (-square_high, -square_low))
    tan_r = high - correction
    tan_r_low = (high - tan_r) - correction
    # Numerator T_j + tan r and denominator 1 - T_j tan r, each as high + low part.
    table_high, table_low = _TAN_HI[index], _TAN_LO[index]
    table_high_parts = _veltkamp_split(table_high)
    tan_r_high, tan_r_rest = _veltkamp_split(tan_r)
    numerator = tan_r + table_high
    numerator_low = ((tan_r - (numerator - table_high)) + table_low) + tan_r_low
    denominator = fma(-tan_r, table_high, 1.0, table_high_parts, (-tan_r_high, -tan_r_rest))
    denominator_error = fma(tan_r, table_high, denominator - 1.0, table_high_parts, (tan_r_high, tan_r_rest))
    denominator_low = fma(
        tan_r,
        table_low,
        fma(tan_r_low, table_high, denominator_error, table_high_parts),
        None,
        (tan_r_high, tan_r_rest),
    )
    # The quotient: vrcp14pd, one Newton step on the reciprocal, one on the quotient.
    estimate = rcp14(denominator)
    estimate_parts = _veltkamp_split(estimate)
    residual = fma(denominator_low, estimate, _estimate_residual(denominator, estimate), estimate_parts)
    reciprocal = fma(residual, estimate, estimate, estimate_parts)
    quotient = numerator * reciprocal
    quotient_high, quotient_low = _veltkamp_split(quotient)
    remainder = (
        fma(
            denominator_low,
            -quotient,
            fma(denominator, quotient, -numerator, (quotient_high, quotient_low)),
            (-quotient_high, -quotient_low),
        )
        - numerator_low
    )
    result = fma(-reciprocal, remainder, quotient)
    if replayed.all():  # the usual case: no angle needs numpy's own value
        return result
    return np.where(replayed, result, np.tan(x))


# Up to this many angles the float replay is the faster (about 12 us an angle, the numpy one 300 us a call).
_FLOAT_REPLAY_MAX_ANGLES = 20
# The constant factors' Veltkamp splits, and the table as (T_j high, T_j low) pairs with theirs.
_SIXTEEN_OVER_PI_SPLIT = _veltkamp_split(_SIXTEEN_OVER_PI)
_PI16_SPLITS = tuple((part, _veltkamp_split(part)) for part in _PI16_PARTS)
_TAN_POLYNOMIAL_SPLIT = _veltkamp_split(_TAN_POLYNOMIAL[0])
_TAN_TABLE = tuple(
    (high, _veltkamp_split(high), low, _veltkamp_split(low))
    for high, low in zip(_TAN_HI.tolist(), _TAN_LO.tolist(), strict=True)
)


def _svml_tan_float(angle: float) -> float:
    """Return `svml_tan_emulated` of one Python float: the same operations in the same order."""
    if not _REPLAY_LOW <= abs(angle) < _REPLAY_HIGH:
        return float(np.tan(angle))  # outside the replay's domain, as the numpy replay takes it
    fma = _fused_multiply_add_float
    shifted = fma(angle, _SIXTEEN_OVER_PI, _SHIFTER, _SIXTEEN_OVER_PI_SPLIT)
    count = shifted - _SHIFTER
    (pi_1, split_1), (pi_2, split_2), (pi_3, split_3) = _PI16_SPLITS
    first = fma(-count, pi_1, angle, split_1)
    second = fma(-count, pi_2, first, split_2)
    high = fma(-count, pi_3, second, split_3)
    low = fma(-count, pi_2, first - second, split_2) - fma(pi_3, count, high - second)
    square = high * high
    polynomial = fma(square, _TAN_POLYNOMIAL[0], _TAN_POLYNOMIAL[1], _TAN_POLYNOMIAL_SPLIT)
    for coefficient in _TAN_POLYNOMIAL[2:]:
        polynomial = fma(square, polynomial, coefficient)
    correction = fma(-square, polynomial * high, -low)
    tan_r = high - correction
    tan_r_low = (high - tan_r) - correction
    # j = N mod 16: N's low bits are the shifted value's (|N| <= 7 here, far below the shifter's 2^51).
    table_high, high_split, table_low, low_split = _TAN_TABLE[int(count) & 15]
    numerator = tan_r + table_high
    numerator_low = ((tan_r - (numerator - table_high)) + table_low) + tan_r_low
    denominator = fma(-tan_r, table_high, 1.0, high_split)
    denominator_error = fma(tan_r, table_high, denominator - 1.0, high_split)
    denominator_low = fma(
        tan_r, table_low, fma(tan_r_low, table_high, denominator_error, high_split), low_split
    )
    estimate = rcp14_float(denominator)
    residual = fma(denominator_low, estimate, fma(-denominator, estimate, 1.0))
    reciprocal = fma(residual, estimate, estimate)
    quotient = numerator * reciprocal
    remainder = fma(-quotient, denominator_low, fma(quotient, denominator, -numerator)) - numerator_low
    return fma(-reciprocal, remainder, quotient)


# Angles where SVML's tan is one ulp off the C library's, with SVML's results: numpy is SVML here exactly
# when it gives these.
_SVML_PROBE_ANGLES = np.array([-0.013954, 0.447353, 0.998676, 0.121004])
_SVML_PROBE_TAN = np.array(
    [
        float.fromhex(h)
        for h in (
            "-0x1.c9463be8c3602p-7",
            "0x1.eb4f448fbc89dp-2",
            "0x1.8d89a729ffdc5p+0",
            "0x1.f210ce4271896p-4",
        )
    ]
)
NUMPY_TAN_IS_SVML = bool(np.array_equal(np.tan(_SVML_PROBE_ANGLES), _SVML_PROBE_TAN))


def tan_avx512(angle: npt.ArrayLike) -> FloatArray:
    """Return np.tan(angle) as the devkit computed it on the AVX-512 machines of the official results:
    numpy's own where numpy runs SVML (exact, and faster), the replay elsewhere."""
    if NUMPY_TAN_IS_SVML:
        return np.tan(angle)
    return svml_tan_emulated(angle)
