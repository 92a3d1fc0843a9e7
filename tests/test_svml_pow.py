"""numpy's AVX-512 (SVML) power and the directed roundings its replay needs, reproduced from float64 operations.

Where numpy runs SVML (an AVX-512 host) the replay is compared with numpy's own results on millions of bases;
on every host with SVML's bits recorded on an AVX-512 host (fixtures/svml-pow: negative, huge and tiny bases,
near-ties, special values, the scalar path's whole range) and with the values in its probe;
test_host_independence compares whole runs with and without numpy's AVX-512 path.
"""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from scorer.directed_rounding import (
    add_downward,
    add_toward_zero,
    fused_multiply_add_toward_zero,
    multiply_toward_zero,
)
from scorer.geometry import FloatArray
from scorer.svml_pow import (
    _SVML_PROBE_BASES,
    _SVML_PROBE_POWERS,
    NUMPY_POWER_IS_SVML,
    svml_power_emulated,
)

needs_svml = pytest.mark.skipif(not NUMPY_POWER_IS_SVML, reason="numpy does not run SVML on this host")
RECORDED = Path(__file__).parent / "fixtures" / "svml-pow" / "scalar_path.npz"


def recorded_powers() -> list[tuple[float, FloatArray, FloatArray]]:
    """Return (exponent, bases, SVML's powers) per exponent recorded in the fixture."""
    with np.load(RECORDED) as recorded:
        bases, exponents, powers = recorded["bases"], recorded["exponents"], recorded["powers"]
    return [
        (float(exponent), bases[same], powers[same])
        for exponent in np.unique(exponents.view(np.int64)).view(np.float64)
        for same in [exponents.view(np.int64) == exponent.view(np.int64)]
    ]


def test_directed_roundings_bracket_the_exact_value_within_an_ulp() -> None:
    """Each result is the float next to the exact value on its side: toward zero never beyond it in magnitude,
    downward never above it, and within one ulp (checked in exact rational arithmetic)."""
    rng = np.random.default_rng(3)
    a = rng.standard_normal(2000) * np.exp2(rng.integers(-30, 30, 2000))
    b = rng.standard_normal(2000)
    c = rng.standard_normal(2000) * np.exp2(rng.integers(-60, 10, 2000))
    fa, fb, fc = ([Fraction(value) for value in array.tolist()] for array in (a, b, c))
    toward_zero = {
        "multiply": (multiply_toward_zero(a, b), [x * y for x, y in zip(fa, fb, strict=True)]),
        "fma": (
            fused_multiply_add_toward_zero(a, b, c),
            [x * y + z for x, y, z in zip(fa, fb, fc, strict=True)],
        ),
        "add": (add_toward_zero(a, c), [x + z for x, z in zip(fa, fc, strict=True)]),
    }
    for name, (rounded, exact) in toward_zero.items():
        for value, e in zip(rounded.tolist(), exact, strict=True):
            assert abs(Fraction(value)) <= abs(e) < abs(Fraction(value)) + Fraction(math.ulp(value)), name
    for value, e in zip(
        add_downward(a, c).tolist(), [x + z for x, z in zip(fa, fc, strict=True)], strict=True
    ):
        assert Fraction(value) <= e < Fraction(value) + Fraction(math.ulp(value))


def test_the_svml_power_probe_is_svml_and_not_libm() -> None:
    """The probe that tells whether numpy runs SVML's pow: the replay gives its values, libm does not."""
    assert np.array_equal(svml_power_emulated(_SVML_PROBE_BASES, 10), _SVML_PROBE_POWERS)
    assert not any(
        math.pow(base, 10) == power for base, power in zip(_SVML_PROBE_BASES, _SVML_PROBE_POWERS, strict=True)
    )


def test_svml_power_is_within_an_ulp_of_the_exact_tenth_power_and_not_correctly_rounded() -> None:
    bases = np.random.default_rng(4).uniform(0, 2, 5000)
    ours = svml_power_emulated(bases, 10)
    exact = [Fraction(base) ** 10 for base in bases.tolist()]
    assert all(
        abs(Fraction(value) - e) < Fraction(math.ulp(value)) for value, e in zip(ours, exact, strict=True)
    )
    assert (
        0.01 < np.mean([value != float(e) for value, e in zip(ours, exact, strict=True)]) < 0.1
    )  # about 5 %


@needs_svml
def test_the_power_replay_gives_numpys_svml_bits() -> None:
    """The IDM's (v / v0) ** 10 over its whole reachable range (the reference scenes reach v / v0 = 5), near 1
    and near every table band, then the main path's whole range and other exponents."""
    rng = np.random.default_rng(5)
    bands = (1 / (1 + np.arange(33) / 32))[:, None] * rng.uniform(1 - 1e-9, 1 + 1e-9, (33, 300))
    bases = np.concatenate(
        [
            rng.uniform(0, 2, 1_000_000),
            rng.uniform(2, 8, 300_000),
            rng.uniform(0.97, 1.03, 300_000),
            np.concatenate([bands.ravel(), bands.ravel() * 2, bands.ravel() / 2]),
            np.exp2(rng.uniform(-100, 100, 300_000)),
        ]
    )
    for exponent in (10, 10.0):
        assert np.array_equal(
            svml_power_emulated(bases, exponent).view(np.int64), np.power(bases, exponent).view(np.int64)
        )
    for exponent in (2.5, -3.0, 0.3):
        others = bases[:200_000]
        assert np.array_equal(
            svml_power_emulated(others, exponent).view(np.int64), np.power(others, exponent).view(np.int64)
        )


@needs_svml
def test_the_scalar_path_replay_gives_numpys_svml_bits() -> None:
    """Negative bases (the IDM's where the ego's speed is negative) and the bases whose tenth power leaves the
    main path: beyond 2^+-102, subnormal, over- and underflowing; odd exponents for the sign."""
    rng = np.random.default_rng(6)
    subnormal = rng.integers(1, 2**52, 50_000).view(np.float64)
    bases = np.concatenate(
        [
            -rng.uniform(0, 2, 1_000_000),
            -rng.uniform(2, 8, 200_000),
            np.exp2(rng.uniform(-1075, 1024, 200_000)) * rng.choice([-1.0, 1.0], 200_000),
            np.exp2(rng.uniform(-110, -101.5, 200_000)) * rng.choice([-1.0, 1.0], 200_000),
            np.exp2(rng.uniform(101.5, 103, 200_000)) * rng.choice([-1.0, 1.0], 200_000),
            subnormal,
            -subnormal,
        ]
    )
    with np.errstate(over="ignore", under="ignore"):
        for exponent in (10, 3.0, 11.0, -3.0):
            assert np.array_equal(
                svml_power_emulated(bases, exponent).view(np.int64), np.power(bases, exponent).view(np.int64)
            )


def test_the_power_replay_gives_svmls_recorded_bits() -> None:
    """On every host: the recorded near-ties (|x| ** n within 2^-12 ulp of a midpoint, normal and subnormal
    results), random negative, huge, tiny and subnormal bases, and special bases and exponents."""
    with np.errstate(all="ignore"):
        for exponent, bases, powers in recorded_powers():
            assert np.array_equal(svml_power_emulated(bases, exponent).view(np.int64), powers.view(np.int64))


@needs_svml
def test_the_recorded_powers_are_numpys_svml_bits() -> None:
    with np.errstate(all="ignore"):
        for exponent, bases, powers in recorded_powers():
            assert np.array_equal(np.power(bases, exponent).view(np.int64), powers.view(np.int64))


def test_a_negative_base_is_not_the_main_paths_magnitude_with_a_sign() -> None:
    """SVML's scalar path rounds otherwise than its main path on about 5 % of bases: why negative bases need a
    replay of their own."""
    bases = np.random.default_rng(7).uniform(0.1, 2, 10_000)
    assert 0.01 < np.mean(svml_power_emulated(-bases, 10) != svml_power_emulated(bases, 10)) < 0.1
    assert 0.01 < np.mean(-svml_power_emulated(-bases, 11) != svml_power_emulated(bases, 11)) < 0.1


def test_the_power_replay_keeps_the_shape() -> None:
    assert svml_power_emulated(np.array([[0.5, -1.5]]), 10).shape == (1, 2)
    assert svml_power_emulated(-0.5, 10).shape == ()
