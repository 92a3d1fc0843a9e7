"""numpy's AVX-512 (SVML) tan and the `vrcp14pd` estimate SVML divides with, reproduced from float64 operations.

Where numpy runs SVML (an AVX-512 host) the replays are compared with numpy's own results; elsewhere with the
SVML values recorded here, and test_host_independence compares whole runs with and without numpy's AVX-512 path.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from scorer.geometry import (
    NUMPY_ARCTAN2_IS_SVML,
    FloatArray,
    _estimate_residual,
    _fused_multiply_add,
    _fused_multiply_add_float,
    svml_arctan2_emulated,
)
from scorer.rcp14 import rcp14, rcp14_float, significands
from scorer.svml_tan import (
    _FLOAT_REPLAY_MAX_ANGLES,
    _PI16_PARTS,
    _SHIFTER,
    _SIXTEEN_OVER_PI,
    _SVML_PROBE_ANGLES,
    _SVML_PROBE_TAN,
    NUMPY_TAN_IS_SVML,
    _nearest_sixteenth,
    _reduced_angle,
    _svml_tan_float,
    svml_tan_emulated,
)

needs_svml = pytest.mark.skipif(not NUMPY_TAN_IS_SVML, reason="numpy does not run SVML on this host")
libm_tan = np.vectorize(math.tan, otypes=[np.float64])


def test_every_rcp14_significand_is_within_the_architectural_bound_and_falls() -> None:
    """`vrcp14pd` promises a relative error below 2^-14 for every divisor of a table entry's interval."""
    lower = 1 + np.arange(2**16) / 2**16  # the interval [lower, lower + 2^-16) of entry i
    upper = lower + 2.0**-16
    table = significands()
    assert np.all(np.abs(table * lower - 1) < 2.0**-14)
    assert np.all(np.abs(table * upper - 1) < 2.0**-14)
    assert np.all(np.diff(table) <= 0) and table[0] == float.fromhex("0x1.fffcp-1")


def test_rcp14_scales_by_the_exponent_and_is_exact_on_powers_of_two() -> None:
    rng = np.random.default_rng(0)
    divisors = rng.uniform(1, 2, 1000) * 2.0 ** rng.integers(-20, 20, 1000) * rng.choice([-1.0, 1.0], 1000)
    estimates = rcp14(divisors)
    assert np.all(np.abs(estimates * divisors - 1) < 2.0**-14)
    assert [rcp14_float(value) for value in divisors.tolist()] == estimates.tolist()
    powers = np.array([1.0, 2.0, 0.25, -8.0, 2.0**-40])
    assert rcp14(powers).tolist() == (1 / powers).tolist()
    # Only the top 16 bits of the significand index the table: the lower ones change nothing.
    assert rcp14(np.array([1.5, np.nextafter(1.5 + 2.0**-16, 0)])).tolist() == [rcp14_float(1.5)] * 2


def test_the_svml_tan_probe_is_svml_and_not_libm() -> None:
    """The probe that tells whether numpy runs SVML's tan: the replay gives its values, libm does not."""
    assert np.array_equal(svml_tan_emulated(_SVML_PROBE_ANGLES), _SVML_PROBE_TAN)
    assert not np.any(libm_tan(_SVML_PROBE_ANGLES) == _SVML_PROBE_TAN)


def test_svml_tan_differs_from_libm_by_at_most_one_ulp_on_steering_angles() -> None:
    angles = np.random.default_rng(1).uniform(-np.pi / 3, np.pi / 3, 200_000)
    ours, libm = svml_tan_emulated(angles), libm_tan(angles)
    assert np.all(np.abs(ours - libm) <= np.spacing(np.abs(libm)))
    assert 0.002 < np.mean(ours != libm) < 0.02  # SVML is not correctly rounded: about 0.5 % differ


@needs_svml
def test_the_tan_replay_gives_numpys_svml_bits() -> None:
    rng = np.random.default_rng(2)
    angles = np.concatenate(
        [
            rng.uniform(-1.4, 1.4, 1_000_000),
            rng.uniform(-1e-4, 1e-4, 100_000),
            (
                (np.pi / 16 * np.arange(-7, 8))[:, None] + rng.uniform(-1e-6, 1e-6, (15, 200))
            ).ravel(),  # band edges
        ]
    )
    assert np.array_equal(svml_tan_emulated(angles).view(np.int64), np.tan(angles).view(np.int64))


def test_the_tan_replay_keeps_numpys_value_outside_its_domain() -> None:
    special = np.array([0.0, -0.0, 5e-324, -1e-310, 2.0**-301, 1.4, -1.5, 3.0, 1e300, np.inf, np.nan])
    with np.errstate(invalid="ignore"):
        assert np.array_equal(svml_tan_emulated(special), np.tan(special), equal_nan=True)
    assert np.signbit(svml_tan_emulated(np.array([-0.0])))[0]
    assert svml_tan_emulated(np.array([[0.5, -0.5]])).shape == (1, 2)


def _ulps_around(values: FloatArray, steps: int) -> FloatArray:
    """Return each value and its `steps` neighbours either side, one ulp apart."""
    around = [values]
    for direction in (np.inf, -np.inf):
        neighbour = values
        for _ in range(steps):
            neighbour = np.nextafter(neighbour, direction)
            around.append(neighbour)
    return np.concatenate(around)


def _hard_angles() -> FloatArray:
    """Angles in and around the replay's domain, of both signs: random ones, magnitudes from 2^-320 to 8, a few
    ulps around its bounds 2^-300 and 1.4, around every multiple of pi/16 and every midpoint between two (where
    N changes), subnormals, zeros, huge values, infinities and NaN."""
    rng = np.random.default_rng(3)
    sixteenths = np.pi / 16 * np.arange(-8, 8.5, 0.5)
    subnormals = rng.integers(1, 2**52, 1_000).view(np.float64)
    unsigned = np.concatenate(
        [
            2.0 ** rng.uniform(-320, 3, 60_000),
            _ulps_around(np.array([2.0**-300, 1.4]), 8),
            subnormals,
            [0.0, 5e-324, 2.0**-1022, 1e300, np.finfo(np.float64).max, np.inf, np.nan],
        ]
    )
    return np.concatenate(
        [
            rng.uniform(-1.4, 1.4, 100_000),
            _ulps_around(sixteenths, 8),
            (sixteenths[:, None] + rng.uniform(-1e-6, 1e-6, (len(sixteenths), 200))).ravel(),
            unsigned,
            -unsigned,
        ]
    )


@pytest.fixture(scope="module")
def hard_tan() -> tuple[FloatArray, FloatArray]:
    """The hard angles and their tan from the float replay, one angle a call."""
    angles = _hard_angles()
    with np.errstate(invalid="ignore"):
        return angles, np.array([_svml_tan_float(angle) for angle in angles.tolist()], dtype=np.float64)


def test_the_float_tan_replay_gives_the_numpy_replays_bits(hard_tan: tuple[FloatArray, FloatArray]) -> None:
    angles, floats = hard_tan
    with np.errstate(invalid="ignore"):
        replayed = svml_tan_emulated(angles)  # more angles than the float replay takes: numpy's
    assert np.array_equal(floats.view(np.int64), replayed.view(np.int64))


@needs_svml
def test_the_float_tan_replay_gives_numpys_svml_bits(hard_tan: tuple[FloatArray, FloatArray]) -> None:
    angles, floats = hard_tan
    with np.errstate(invalid="ignore"):
        assert np.array_equal(floats.view(np.int64), np.tan(angles).view(np.int64))


def test_a_few_angles_take_the_float_tan_replay_in_any_shape() -> None:
    angles = _hard_angles()[::997]
    with np.errstate(invalid="ignore"):
        replayed = svml_tan_emulated(angles)
        for shape in [(0,), (), (1,), (2, 3), (_FLOAT_REPLAY_MAX_ANGLES,)]:
            size = math.prod(shape)
            few = svml_tan_emulated(angles[:size].reshape(shape))
            assert few.shape == shape and few.dtype == np.float64
            assert np.array_equal(few.ravel().view(np.int64), replayed[:size].view(np.int64))


@pytest.mark.skipif(not NUMPY_ARCTAN2_IS_SVML, reason="numpy does not run SVML on this host")
def test_the_arctan2_replay_gives_numpys_svml_bits_with_rcp14() -> None:
    """With the correctly rounded reciprocal in place of `vrcp14pd`'s refined estimate, about 14 in a million
    of these pairs were one ulp off (among them three headings of the reference scenes' simulations)."""
    rng = np.random.default_rng(0)
    y, x = rng.standard_normal((2, 1_000_000))
    headings = (
        np.array([0.21767055057796555, 0.23824343552500182]),
        np.array([0.9760223006730355, 0.9712054702426487]),
    )
    for y_part, x_part in ((y, x), headings, (np.tile(headings[0], 20), np.tile(headings[1], 20))):
        replayed = svml_arctan2_emulated(y_part, x_part)
        assert np.array_equal(replayed.view(np.int64), np.arctan2(y_part, x_part).view(np.int64))


def test_the_estimates_residual_is_the_emulated_fma() -> None:
    """1 - d r for `vrcp14pd`'s estimate r of 1 / d, formed without an emulated FMA, rounds as the FMA does."""
    rng = np.random.default_rng(4)
    divisors = np.concatenate(
        [
            rng.uniform(1, 2, 200_000) * 2.0 ** rng.integers(-900, 900, 200_000),
            1 + np.arange(2**16) / 2**16,  # every table entry's first divisor
            np.nextafter(1 + np.arange(1, 2**16 + 1) / 2**16, 0),  # and its last
            2.0 ** np.arange(-60, 61),  # exact estimates
        ]
    )
    divisors = np.concatenate([divisors, -divisors])
    estimates = rcp14(divisors)
    residuals = _estimate_residual(divisors, estimates)
    assert np.array_equal(
        residuals.view(np.int64), _fused_multiply_add(-divisors, estimates, 1.0).view(np.int64)
    )


def _fma_of_each_pair(a: FloatArray, b: float, c: FloatArray | float) -> FloatArray:
    """Return fma(a, b, c) of each element alone, on Python floats (the float FMA's rounding to odd)."""
    c_values = np.broadcast_to(c, a.shape).tolist()
    return np.array([_fused_multiply_add_float(x, b, z) for x, z in zip(a.tolist(), c_values, strict=True)])


def test_tans_reduction_without_emulated_fmas_is_svmls() -> None:
    """N = round(x 16/pi) and the reduced angle, formed from exact products where they allow, equal SVML's FMAs
    on random angles, on angles whose product with 16/pi rounds onto a half-integer (where `rint` alone ties to
    even) and on angles next to multiples of pi/16 (where the third part of pi/16 counts)."""
    rng = np.random.default_rng(5)
    halves = (np.arange(-7, 7) + 0.5) * (np.pi / 16)
    ties = _ulps_around(halves, 40)
    angles = np.concatenate([rng.uniform(-1.4, 1.4, 20_000), ties, -ties])
    angles = angles[np.abs(angles) < 1.4]
    assert np.any(np.abs(angles * _SIXTEEN_OVER_PI - np.rint(angles * _SIXTEEN_OVER_PI)) == 0.5)
    count, index = _nearest_sixteenth(angles)
    shifted = _fma_of_each_pair(angles, _SIXTEEN_OVER_PI, _SHIFTER)
    assert np.array_equal(count.view(np.int64), (shifted - _SHIFTER).view(np.int64))
    assert np.array_equal(index, shifted.view(np.int64) & 15)
    near_multiples = _ulps_around(np.pi / 16 * np.arange(-7, 8), 8)
    near_multiples = near_multiples[np.abs(near_multiples) >= 2.0**-300]  # the replay's domain
    for x in (angles, near_multiples, np.concatenate([angles, near_multiples])):
        reduced = _reduced_angle(x, _nearest_sixteenth(x)[0])
        for part, emulated in zip(reduced, _emulated_reduction(x), strict=True):
            assert np.array_equal(part.view(np.int64), emulated.view(np.int64))


def _emulated_reduction(x: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return SVML's r = x - N pi/16 as high and low parts with every FMA emulated (the replay before its
    shortcuts)."""
    shifted = _fused_multiply_add(x, np.full_like(x, _SIXTEEN_OVER_PI), np.full_like(x, _SHIFTER))
    count = shifted - _SHIFTER
    pi_1, pi_2, pi_3 = (np.full_like(x, part) for part in _PI16_PARTS)
    first = _fused_multiply_add(-count, pi_1, x)
    second = _fused_multiply_add(-count, pi_2, first)
    high = _fused_multiply_add(-count, pi_3, second)
    low = _fused_multiply_add(-count, pi_2, first - second) - _fused_multiply_add(pi_3, count, high - second)
    return high, low
