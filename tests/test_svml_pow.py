"""numpy's AVX-512 (SVML) power and the directed roundings its replay needs, reproduced from float64 operations.

Where numpy runs SVML (an AVX-512 host) the replay is compared with numpy's own results on millions of bases;
elsewhere with the SVML values recorded in its probe, and test_host_independence compares whole runs with and
without numpy's AVX-512 path.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from scorer.directed_rounding import (
    add_downward,
    add_toward_zero,
    fused_multiply_add_toward_zero,
    multiply_toward_zero,
)
from scorer.svml_pow import (
    _SVML_PROBE_BASES,
    _SVML_PROBE_POWERS,
    NUMPY_POWER_IS_SVML,
    svml_power_emulated,
)

needs_svml = pytest.mark.skipif(not NUMPY_POWER_IS_SVML, reason="numpy does not run SVML on this host")


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


def test_the_power_replay_keeps_numpys_value_off_its_main_path() -> None:
    special = np.array([0.0, -0.0, -0.5, -1.7, np.inf, -np.inf, np.nan, 5e-324, 1e-310, 2.0**-103, 1e40])
    with np.errstate(all="ignore"):
        assert np.array_equal(svml_power_emulated(special, 10), np.power(special, 10), equal_nan=True)
    assert svml_power_emulated(np.array([[0.5, 1.5]]), 10).shape == (1, 2)
