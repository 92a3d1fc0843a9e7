"""Angles, the ego vehicle's geometry and the nuPlan EgoState rear-axle round trip.

Three angle helpers exist because the devkit uses three (docs/engine.md, "Conventions: angles");
mixing them changes last bits.
"""

from __future__ import annotations

import math
import struct
from typing import Any, TypeVar, cast

import numpy as np
import numpy.typing as npt

from scorer.rcp14 import rcp14, rcp14_float

FloatArray = npt.NDArray[np.floating[Any]]  # float64 in practice; numpy types arithmetic results this wide
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]  # indices and counts

# Chrysler Pacifica (nuplan/common/actor_state/vehicle_parameters.py); docs/engine.md,
# "Conventions: the ego vehicle and its box".
EGO_HALF_WIDTH = 1.1485
EGO_WIDTH = EGO_HALF_WIDTH * 2.0
EGO_FRONT_LENGTH = 4.049
EGO_REAR_LENGTH = 1.127
EGO_LENGTH = EGO_FRONT_LENGTH + EGO_REAR_LENGTH
EGO_HALF_LENGTH = EGO_LENGTH / 2.0
REAR_AXLE_TO_CENTER = EGO_HALF_LENGTH - EGO_REAR_LENGTH
WHEEL_BASE = 3.089


# Constants of numpy's AVX-512 arctan2 (Intel SVML `__svml_atan28_ha`, table `__svml_datan2_ha_data_internal`):
# |y/x| is reduced around c = 0.5, 1, 1.5 or infinity (bands split at 7/16, 11/16, 19/16, 39/16), atan(c) = hi + lo.
_ATAN2_BAND_LIMITS = np.array([0.4375, 0.6875, 1.1875, 2.4375])
_ATAN2_REDUCTION = np.array([0.5, 1.0, 1.5, 1.0])
_ATAN2_BASE_HI = np.array(
    [
        float.fromhex(h)
        for h in (
            "0x1.dac670561bb4fp-2",
            "0x1.921fb54442d18p-1",
            "0x1.f730bd281f69bp-1",
            "0x1.921fb54442d18p+0",
        )
    ]
)
_ATAN2_BASE_LO = np.array(
    [
        float.fromhex(h)
        for h in (
            "0x1.a2b7f222f65e2p-56",
            "0x1.1a62633145c07p-55",
            "0x1.007887af0cbbdp-56",
            "0x1.1a62633145c07p-54",
        )
    ]
)
_PI_HI, _PI_LO = float.fromhex("0x1.921fb54442d18p+1"), float.fromhex("0x1.1a64000000000p-53")
# atan(r) = r + r^3 * P(r^2), P evaluated as two interleaved chains in r^4, highest coefficient first.
# Two interleaved chains in r^4, highest coefficient first (row 0: chain A, row 1: chain B).
_ATAN2_CHAINS = np.array(
    [
        [
            float.fromhex(h)
            for h in (
                "0x1.be4fbe6733718p-7",
                "0x1.6ad5558fe19c9p-5",
                "0x1.e12f1edf7c393p-5",
                "0x1.3b132b731e73ap-4",
                "0x1.c71c719f99f96p-4",
                "0x1.9999999998f43p-3",
            )
        ],
        [
            float.fromhex(h)
            for h in (
                "-0x1.04cd71f92185ep-5",
                "-0x1.a9e755ca13d23p-5",
                "-0x1.1108d326c68edp-4",
                "-0x1.745d119677a4fp-4",
                "-0x1.2492492441a21p-3",
                "-0x1.5555555555552p-2",
            )
        ],
    ]
)
_VELTKAMP = 134217729.0  # 2**27 + 1
_DOUBLE, _DOUBLE_BITS = struct.Struct("<d"), struct.Struct("<q")  # a float's bits, as int64


# The arithmetic below runs on float64 arrays and on Python floats (the same IEEE doubles) alike.
Number = TypeVar("Number", float, FloatArray)


def _two_sum(a: Number, b: Number) -> tuple[Number, Number]:
    total = a + b
    b_part = total - a
    return total, (a - (total - b_part)) + (b - b_part)


def _veltkamp_split(a: Number) -> tuple[Number, Number]:
    scaled = _VELTKAMP * a
    high = scaled - (scaled - a)
    return high, a - high


def _exact_multiply_add(
    a: Number,
    b: Number,
    c: Number,
    b_parts: tuple[Number, Number] | None,
    a_parts: tuple[Number, Number] | None = None,
) -> tuple[Number, Number, Number]:
    """Return (high, tail, error) with a * b + c == high + tail + error exactly and tail + error the low part.

    Exact product (Dekker) and exact sums. Exact for operands whose product does not underflow
    (|a|, |b| >= 1e-100 or zero), which covers every coordinate and angle the engine handles. `a_parts` and
    `b_parts` are the operands' Veltkamp splits where the caller has them (an operand of several products).
    """
    product = a * b
    a_high, a_low = _veltkamp_split(a) if a_parts is None else a_parts
    b_high, b_low = _veltkamp_split(b) if b_parts is None else b_parts
    product_low = ((a_high * b_high - product) + a_high * b_low + a_low * b_high) + a_low * b_low
    high, low = _two_sum(c, product)
    tail, error = _two_sum(low, product_low)
    return high, tail, error


def _ratio_powers(reciprocal: Number, numerator: Number) -> tuple[Number, Number, Number]:
    """Return the reduced ratio from SVML's reciprocal of the reduced denominator, its square and fourth power."""
    ratio = reciprocal * numerator
    ratio_sq = ratio * ratio
    return ratio, ratio_sq, ratio_sq * ratio_sq


def _fused_multiply_add(
    a: FloatArray,
    b: FloatArray | float,
    c: FloatArray | float,
    b_parts: tuple[FloatArray, FloatArray] | tuple[float, float] | None = None,
    a_parts: tuple[FloatArray, FloatArray] | None = None,
) -> FloatArray:
    """Return a * b + c rounded once, as the FMA instruction does, from float64 operations only (`b` and `c`
    may be constants: a float each, `b` with its split).

    The exact sum's low parts are added with rounding to odd, which makes the final rounding correct
    (Boldo & Melquiond, IEEE Trans. Computers 57(4), 2008).
    """
    # Arrays and constants mix here, which the arithmetic's type variable does not express.
    high, tail, error = cast(
        "tuple[FloatArray, FloatArray, FloatArray]",
        _exact_multiply_add(a, b, c, b_parts, a_parts),
    )
    tail = np.where(
        (error != 0) & ((tail.view(np.int64) & 1) == 0), np.nextafter(tail, np.copysign(np.inf, error)), tail
    )
    return high + tail


def _fused_multiply_add_float(
    a: float, b: float, c: float, b_parts: tuple[float, float] | None = None
) -> float:
    """`_fused_multiply_add` of Python floats: the same rounding to odd, by `math.nextafter`."""
    high, tail, error = _exact_multiply_add(a, b, c, b_parts)
    if error != 0 and not _DOUBLE_BITS.unpack(_DOUBLE.pack(tail))[0] & 1:
        tail = math.nextafter(tail, math.copysign(math.inf, error))
    return high + tail


def _estimate_residual(divisor: FloatArray, estimate: FloatArray) -> FloatArray:
    """Return 1 - divisor * estimate rounded once, as fma(-divisor, estimate, 1) gives it, for `rcp14`'s estimate
    of 1 / divisor, without emulating the FMA: the estimate has at most 17 significant bits and each Veltkamp
    half of the divisor at most 26, so both partial products are exact; the estimate lies within 2^-14 of
    1 / divisor, so the high half's product lies within 2^-13 of 1 and 1 minus it is exact (Sterbenz). The
    subtraction of the low half's product rounds the exact value once."""
    high, low = _veltkamp_split(divisor)
    return (1.0 - high * estimate) - low * estimate


def _svml_reciprocal(denominator: FloatArray) -> FloatArray:
    """Return SVML's 1 / denominator: `vrcp14pd`, then two Newton steps r + (1 - d r) r, each an FMA pair
    (the first step's residual from the estimate's few bits, `_estimate_residual`)."""
    estimate = rcp14(denominator)
    estimate_parts = _veltkamp_split(estimate)
    reciprocal = _fused_multiply_add(
        _estimate_residual(denominator, estimate), estimate, estimate, estimate_parts
    )
    reciprocal_parts = _veltkamp_split(reciprocal)
    residual = _fused_multiply_add(-denominator, reciprocal, 1.0, reciprocal_parts)
    return _fused_multiply_add(residual, reciprocal, reciprocal, reciprocal_parts)


def _svml_reciprocal_float(denominator: float) -> float:
    """`_svml_reciprocal` of one Python float."""
    reciprocal = rcp14_float(denominator)
    for _ in range(2):
        error = _fused_multiply_add_float(-denominator, reciprocal, 1.0)
        reciprocal = _fused_multiply_add_float(error, reciprocal, reciprocal)
    return reciprocal


def svml_arctan2_emulated(y: npt.ArrayLike, x: npt.ArrayLike) -> FloatArray:
    """Return np.arctan2(y, x) as numpy computes it on AVX-512 machines, from float64 operations only.

    There numpy (2.x) calls Intel SVML's `__svml_atan28_ha`, which is not correctly rounded: about 7 %
    of results differ by one ulp from the (correctly rounded) libm value numpy uses elsewhere, and
    the official reference results were made on such a machine. This replays SVML's main path with
    emulated FMAs (independent ones stacked into one call), its reciprocal as SVML forms it: `vrcp14pd`'s
    table estimate (`scorer.rcp14`) refined by two Newton steps. It gives this host's SVML bits on every one
    of 1.3e6 random pairs over 12 orders of magnitude (the correctly rounded reciprocal in place of the
    estimate missed about 14 in a million, and moved a simulated state of the reference scenes). Zeros,
    subnormals, huge values, inf and NaN take SVML's special path, where libm's value is the same (zeros)
    or close enough.

    A few pairs go through `_svml_arctan2_float`, the same replay on Python floats: the tracker wraps two
    angles of each proposal a step, and for one pair the numpy replay takes about 0.4 ms where the float
    replay takes 0.02-0.03 ms a pair (a one-token `navsim-lb score` makes 41 such calls of two pairs; tests
    check the bits).
    """
    y, x = np.broadcast_arrays(np.asarray(y, dtype=np.float64), np.asarray(x, dtype=np.float64))
    if y.size <= _FLOAT_REPLAY_MAX_PAIRS:
        pairs = zip(y.ravel().tolist(), x.ravel().tolist(), strict=True)
        return np.array([_svml_arctan2_float(*pair) for pair in pairs], dtype=np.float64).reshape(y.shape)
    abs_x, abs_y = np.abs(x), np.abs(y)
    band = (abs_x[..., None] * _ATAN2_BAND_LIMITS < abs_y[..., None]).sum(axis=-1)
    reduced = band > 0
    base = np.maximum(band - 1, 0)
    slope = _ATAN2_REDUCTION[base]
    beyond = band == len(_ATAN2_BAND_LIMITS)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # atan(y/x) = atan(c) + atan((y - c*x) / (x + c*y)), or atan(inf) + atan(-x/y) beyond 39/16.
        terms = _fused_multiply_add(
            np.stack([slope, -slope]),
            np.stack([abs_y, abs_x]),
            np.where(beyond, 0.0, np.stack([abs_x, abs_y])),
        )
        denominator = np.where(reduced, terms[0], abs_x)
        numerator = np.where(reduced, terms[1], abs_y)
        reciprocal = _svml_reciprocal(denominator)
        ratio, ratio_sq, ratio_4 = _ratio_powers(reciprocal, numerator)
        parts_4 = _veltkamp_split(ratio_4)
        low = reciprocal * _fused_multiply_add(-ratio, denominator, numerator)
        low = np.where(reduced, low + _ATAN2_BASE_LO[base], low)
        chains = np.broadcast_to(_ATAN2_CHAINS[:, :1].reshape(2, *(1,) * ratio.ndim), (2, *ratio.shape))
        for coefficient in _ATAN2_CHAINS[:, 1:].T:
            chains = _fused_multiply_add(chains, ratio_4, coefficient.reshape(2, *(1,) * ratio.ndim), parts_4)
        polynomial = _fused_multiply_add(chains[0], ratio_sq, chains[1]) * ratio_sq
        negative_x = x < 0
        low = np.where(negative_x, low - _PI_LO, low)
        result = ratio + _fused_multiply_add(polynomial, ratio, low)
        result = np.where(reduced, result + _ATAN2_BASE_HI[base], result)
        result = np.where(np.signbit(x), -result, result)
        result = np.copysign(np.where(negative_x, result + _PI_HI, result), y)
    high_x = abs_x.view(np.uint64) >> np.uint64(32)
    high_y = abs_y.view(np.uint64) >> np.uint64(32)
    main_path = (
        (high_x >= 0x00300000) & (high_x < 0x7E000000) & (high_y >= 0x00300000) & (high_y < 0x7E000000)
    )
    if main_path.all():  # the usual case: no pair needs numpy's own value (libm's, about 20 ns a pair)
        return result
    return np.where(main_path, result, np.arctan2(y, x))


# Up to this many pairs the float replay is the faster (it costs 9 us a pair, the numpy one 180 us a call).
_FLOAT_REPLAY_MAX_PAIRS = 16
# The main path's bounds on |x| and |y|: SVML's test of the high word, 0x00300000 <= high < 0x7E000000.
_MAIN_PATH_LOW, _MAIN_PATH_HIGH = 2.0**-1020, 2.0**993
_ATAN2_TABLES = tuple(
    table.tolist() for table in (_ATAN2_BAND_LIMITS, _ATAN2_REDUCTION, _ATAN2_BASE_HI, _ATAN2_BASE_LO)
)
_ATAN2_CHAIN_STEPS = tuple(zip(*_ATAN2_CHAINS.tolist(), strict=True))  # (chain A, chain B) coefficient pairs


def _svml_arctan2_float(y: float, x: float) -> float:
    """Return `svml_arctan2_emulated` of one pair of Python floats: the same operations in the same order,
    a branch for each `np.where` and the stacked FMAs one by one (each rounds alone)."""
    abs_x, abs_y = abs(x), abs(y)
    if not (_MAIN_PATH_LOW <= abs_x < _MAIN_PATH_HIGH and _MAIN_PATH_LOW <= abs_y < _MAIN_PATH_HIGH):
        return float(np.arctan2(y, x))  # SVML's special path, as the numpy replay takes it
    band_limits, reduction, base_hi, base_lo = _ATAN2_TABLES
    band = sum(abs_x * limit < abs_y for limit in band_limits)
    base = max(band - 1, 0)
    slope = reduction[base]
    if band > 0:
        beyond = band == len(band_limits)
        denominator = _fused_multiply_add_float(slope, abs_y, 0.0 if beyond else abs_x)
        numerator = _fused_multiply_add_float(-slope, abs_x, 0.0 if beyond else abs_y)
    else:
        denominator, numerator = abs_x, abs_y
    reciprocal = _svml_reciprocal_float(denominator)
    ratio, ratio_sq, ratio_4 = _ratio_powers(reciprocal, numerator)
    parts_4 = _veltkamp_split(ratio_4)
    low = reciprocal * _fused_multiply_add_float(-ratio, denominator, numerator)
    if band > 0:
        low = low + base_lo[base]
    chain_a, chain_b = _ATAN2_CHAIN_STEPS[0]
    for coefficient_a, coefficient_b in _ATAN2_CHAIN_STEPS[1:]:
        chain_a = _fused_multiply_add_float(chain_a, ratio_4, coefficient_a, parts_4)
        chain_b = _fused_multiply_add_float(chain_b, ratio_4, coefficient_b, parts_4)
    polynomial = _fused_multiply_add_float(chain_a, ratio_sq, chain_b) * ratio_sq
    if x < 0:
        low = low - _PI_LO
    result = ratio + _fused_multiply_add_float(polynomial, ratio, low)
    if band > 0:
        result = result + base_hi[base]
    if math.copysign(1.0, x) < 0:
        result = -result
    if x < 0:
        result = result + _PI_HI
    return math.copysign(result, y)


# Pairs where SVML's arctan2 is one ulp off the correctly rounded value, with SVML's results: numpy is SVML
# here exactly when it gives these.
_SVML_PROBE_Y = np.array([0.4204452380655215, -0.9582652054360887, -1.7321348424395848, -0.7133133716322436])
_SVML_PROBE_X = np.array([-0.6751644318458926, -0.8558898003024131, 0.11223573050766027, 0.07973264584871048])
_SVML_PROBE_ARCTAN2 = np.array(
    [
        float.fromhex(h)
        for h in (
            "0x1.4ad510f594a40p+1",
            "-0x1.26609823b8df4p+1",
            "-0x1.818f274220f8ap+0",
            "-0x1.75a0841df7314p+0",
        )
    ]
)
NUMPY_ARCTAN2_IS_SVML = bool(np.array_equal(np.arctan2(_SVML_PROBE_Y, _SVML_PROBE_X), _SVML_PROBE_ARCTAN2))


def arctan2_avx512(y: npt.ArrayLike, x: npt.ArrayLike) -> FloatArray:
    """Return np.arctan2(y, x) as the devkit computed it on the AVX-512 machine of the official results:
    numpy's own where numpy runs SVML (exact, and faster), the emulation elsewhere."""
    if NUMPY_ARCTAN2_IS_SVML:
        return np.arctan2(y, x)
    return svml_arctan2_emulated(y, x)


def normalize_angle(angle: npt.ArrayLike) -> FloatArray:
    """Return the angle wrapped to (-pi, pi] via atan2, with the devkit's arctan2.

    PDM's `normalize_angle`, whose name (and American spelling) this keeps so the two can be matched.
    """
    angle = np.asarray(angle, dtype=np.float64)
    return arctan2_avx512(np.sin(angle), np.cos(angle))


def principal_value(angle: npt.ArrayLike) -> FloatArray:
    """Return the angle wrapped to [-pi, pi) by floor-mod (nuPlan's `principal_value`); non-finite raises."""
    angle = np.asarray(angle, dtype=np.float64)
    if not np.all(np.isfinite(angle)):
        raise ValueError("non-finite heading in the simulation")
    return (angle + np.pi) % (2 * np.pi) - np.pi


def principal_value_of(angle: float) -> float:
    """Return `principal_value` of one float, in Python floats: the same operations, rounded alike (Python's
    float `%` adjusts C's fmod as numpy's remainder does), without numpy's per-call cost."""
    if not math.isfinite(angle):
        raise ValueError("non-finite heading in the simulation")
    return (angle + math.pi) % (2 * math.pi) - math.pi


def rear_axle_round_trip(
    x: npt.ArrayLike, y: npt.ArrayLike, heading: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Return the rear axle an EgoState built from this rear-axle pose reports back.

    nuPlan stores the box centre and derives the rear axle from it, which can move x, y by one ulp
    (docs/engine.md, "Conventions: the rear-axle round trip").
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    heading = np.asarray(heading, dtype=np.float64)
    cos_h, sin_h = np.cos(heading), np.sin(heading)
    center_x = x + REAR_AXLE_TO_CENTER * cos_h
    center_y = y + REAR_AXLE_TO_CENTER * sin_h
    return center_x + (-REAR_AXLE_TO_CENTER) * cos_h, center_y + (-REAR_AXLE_TO_CENTER) * sin_h


def ego_center(x: npt.ArrayLike, y: npt.ArrayLike, heading: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Return the ego box centre for rear-axle poses.

    See docs/engine.md, "Conventions: the ego vehicle and its box".
    """
    heading = np.asarray(heading, dtype=np.float64)
    return (
        np.asarray(x, dtype=np.float64) + REAR_AXLE_TO_CENTER * np.cos(heading),
        np.asarray(y, dtype=np.float64) + REAR_AXLE_TO_CENTER * np.sin(heading),
    )


# Corner order of every box in the engine: front-left, rear-left, rear-right, front-right
# (docs/engine.md, "Conventions: state arrays").
# A box's corners FL, RL, RR, FR: the signs of their longitudinal and lateral offsets.
CORNER_SIGNS = ((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0))
_CORNER_SIGNS = np.array(CORNER_SIGNS)


def box_corners(
    center_x: npt.ArrayLike,
    center_y: npt.ArrayLike,
    heading: npt.ArrayLike,
    half_length: npt.ArrayLike,
    half_width: npt.ArrayLike,
) -> FloatArray:
    """Return the 4 corners (..., 4, 2) of boxes, FL, RL, RR, FR, with PDM's translation formula.

    See docs/engine.md, "Conventions: the ego vehicle and its box".
    """
    center_x = np.asarray(center_x, dtype=np.float64)[..., None]
    center_y = np.asarray(center_y, dtype=np.float64)[..., None]
    heading = np.asarray(heading, dtype=np.float64)[..., None]
    lon = _CORNER_SIGNS[:, 0] * np.asarray(half_length, dtype=np.float64)[..., None]
    lat = _CORNER_SIGNS[:, 1] * np.asarray(half_width, dtype=np.float64)[..., None]
    corner_x = center_x + (lat * np.cos(heading + math.pi / 2) + lon * np.cos(heading))
    corner_y = center_y + (lat * np.sin(heading + math.pi / 2) + lon * np.sin(heading))
    return np.stack([corner_x, corner_y], axis=-1)
