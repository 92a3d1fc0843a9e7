"""numpy's AVX-512 (SVML) arccos and the `vrsqrt14pd` estimate it starts from, reproduced from float64 operations.

Where numpy runs SVML (an AVX-512 host) the replay is compared with numpy's own results on millions of
arguments; elsewhere with the SVML values recorded in its probe, and test_host_independence compares whole runs
(NC and TTC take the arccos) with and without numpy's AVX-512 path.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from scorer.rsqrt14 import rsqrt14, significands
from scorer.svml_acos import (
    _SVML_PROBE_ARCCOS,
    _SVML_PROBE_ARGUMENTS,
    NUMPY_ARCCOS_IS_SVML,
    svml_arccos_emulated,
)

needs_svml = pytest.mark.skipif(not NUMPY_ARCCOS_IS_SVML, reason="numpy does not run SVML on this host")


def test_every_rsqrt14_significand_is_within_the_architectural_bound_and_falls() -> None:
    """`vrsqrt14pd` promises a relative error below 2^-14 over each entry's interval of arguments."""
    table = significands()
    for parity in (0, 1):
        lower = 2.0**parity * (1 + np.arange(2**15) / 2**15)
        entries = table[parity * 2**15 : (parity + 1) * 2**15]
        for argument in (lower, lower * (1 + 2.0**-15)):
            assert np.all(np.abs(entries * np.sqrt(argument) - 1) < 2.0**-14)
        assert np.all(np.diff(entries) <= 0)


def test_rsqrt14_halves_the_exponent_and_is_exact_on_even_powers_of_two() -> None:
    rng = np.random.default_rng(0)
    arguments = rng.uniform(1, 4, 1000) * 4.0 ** rng.integers(-100, 100, 1000)
    estimates = rsqrt14(arguments)
    assert np.all(np.abs(estimates * np.sqrt(arguments) - 1) < 2.0**-14)
    # Scaling the argument by 4 halves the estimate: only the parity and the top 15 fraction bits index it.
    assert np.array_equal(rsqrt14(arguments * 4), estimates / 2)
    assert rsqrt14(np.array([1.0, 0.25, 2.0**-40, 16.0])).tolist() == [1.0, 2.0, 2.0**20, 0.25]
    assert rsqrt14(np.array([2.0]))[0] != 2**-0.5  # an odd power takes the table
    assert (
        rsqrt14(np.array([1.0 + 2.0**-15, np.nextafter(1.0 + 2.0**-14, 0)])).tolist()
        == [significands()[1]] * 2
    )


def test_the_svml_arccos_probe_is_svml_and_not_libm() -> None:
    """The probe that tells whether numpy runs SVML's arccos: the replay gives its values, libm does not."""
    assert np.array_equal(svml_arccos_emulated(_SVML_PROBE_ARGUMENTS), _SVML_PROBE_ARCCOS)
    assert not any(
        math.acos(x) == value for x, value in zip(_SVML_PROBE_ARGUMENTS, _SVML_PROBE_ARCCOS, strict=True)
    )


@needs_svml
def test_the_arccos_replay_gives_numpys_svml_bits() -> None:
    """The whole domain, both branches near their border |x| = 1/2, near -1, 0 and 1, and the cosines of
    angles near NC's and TTC's bounds (30 and 150 degrees)."""
    rng = np.random.default_rng(7)
    bounds = np.cos(np.deg2rad([30.0, 150.0]))[:, None] + rng.uniform(-1e-9, 1e-9, (2, 100_000))
    arguments = np.concatenate(
        [
            rng.uniform(-1, 1, 1_000_000),
            rng.uniform(-1e-3, 1e-3, 100_000) + 0.5,
            rng.uniform(-1e-3, 1e-3, 100_000) - 0.5,
            1 - rng.uniform(0, 1e-6, 100_000),
            rng.uniform(0, 1e-6, 100_000) - 1,
            rng.uniform(-1e-12, 1e-12, 100_000),
            bounds.ravel(),
            [0.5, -0.5],
        ]
    )
    assert np.array_equal(svml_arccos_emulated(arguments).view(np.int64), np.arccos(arguments).view(np.int64))


def test_the_arccos_replay_keeps_numpys_value_off_its_domain() -> None:
    """At and past the domain's ends, and at 0, SVML and the C library agree: the replay gives both's value.
    (Inside it they differ, at 1/2 say: the SVML tests above compare there.)"""
    values = np.array([0.0, -0.0, 1.0, -1.0, 5e-324, 1.0000001, -2.0, np.inf, np.nan])
    with np.errstate(invalid="ignore"):
        assert np.array_equal(svml_arccos_emulated(values), np.arccos(values), equal_nan=True)
    assert svml_arccos_emulated(np.array([[0.5, -0.5]])).shape == (1, 2)
