"""numpy's AVX-512 (SVML) exp reproduced from float64 operations: its main path and its scalar path.

Where numpy runs SVML (an AVX-512 host) the replay is compared with numpy's own results on millions of
arguments; elsewhere with the SVML values recorded in its probe, and test_host_independence compares the
two-stage weights with and without numpy's AVX-512 path.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from scorer.svml_exp import (
    _MAIN_PATH_BOUND,
    _SUBNORMAL_BELOW,
    _SVML_PROBE_ARGUMENTS,
    _SVML_PROBE_EXP,
    EXP2_64THS_HI,
    EXP2_64THS_LO,
    NUMPY_EXP_IS_SVML,
    svml_exp_emulated,
)

needs_svml = pytest.mark.skipif(not NUMPY_EXP_IS_SVML, reason="numpy does not run SVML on this host")


def test_the_svml_exp_probe_is_svml_and_not_libm() -> None:
    """The probe that tells whether numpy runs SVML's exp: the replay gives its values, libm does not."""
    assert np.array_equal(svml_exp_emulated(_SVML_PROBE_ARGUMENTS), _SVML_PROBE_EXP)
    assert not any(
        math.exp(x) == value for x, value in zip(_SVML_PROBE_ARGUMENTS, _SVML_PROBE_EXP, strict=True)
    )


def test_the_table_is_two_to_the_sixty_fourths_with_a_relative_low_part() -> None:
    """high (1 + low) is within 2^-106 of 2^(i/64) relatively: its 64th power over 2^i is 1 to within 64 such
    errors (the low part is relative: SVML forms high + high (low + e^r - 1))."""
    for i, (high, low) in enumerate(zip(EXP2_64THS_HI.tolist(), EXP2_64THS_LO.tolist(), strict=True)):
        ratio = (Fraction(high) * (1 + Fraction(low))) ** 64 / 2**i
        assert abs(ratio - 1) < Fraction(64, 2**106), i


@needs_svml
def test_the_exp_replay_gives_numpys_svml_bits() -> None:
    """The Gaussians' exponents -d^2 / 0.2 (d up to 12.2 m: every result above 0), the main path's bound and
    the subnormal results' bound, and the whole range up to the overflow threshold."""
    rng = np.random.default_rng(6)
    bound_nearby = np.concatenate(
        [
            rng.uniform(-1e-9, 1e-9, 50_000) + edge
            for edge in (-_MAIN_PATH_BOUND, _MAIN_PATH_BOUND, _SUBNORMAL_BELOW)
        ]
    )
    arguments = np.concatenate(
        [
            -(rng.uniform(0, 12.2, 1_000_000) ** 2) / 0.2,
            rng.uniform(-746, 710, 1_000_000),
            rng.uniform(-1, 1, 200_000),
            bound_nearby,
        ]
    )
    with np.errstate(over="ignore"):
        assert np.array_equal(svml_exp_emulated(arguments).view(np.int64), np.exp(arguments).view(np.int64))


def test_the_exp_replay_keeps_numpys_value_beyond_its_thresholds() -> None:
    special = np.array([0.0, -0.0, 1e-320, np.inf, -np.inf, np.nan, -746.0, -1000.0, 710.0, 1e300])
    with np.errstate(over="ignore"):
        assert np.array_equal(svml_exp_emulated(special), np.exp(special), equal_nan=True)
    assert svml_exp_emulated(np.array([[0.5, -800.0]])).shape == (1, 2)
