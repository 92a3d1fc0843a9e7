"""How close a number must come to the official devkit's: exactly under the official results' OpenBLAS
kernels (what `scorer.blas` selects where the CPU runs them), else within the last bits `pinv` moves."""

from __future__ import annotations

import math

from scorer.blas import DEVKIT_KERNELS, blas_kernels

UNDER_DEVKIT_KERNELS = blas_kernels() == (DEVKIT_KERNELS,)


def devkit_tolerance(elsewhere: float) -> float:
    """Return 0 under the devkit's kernels, else `elsewhere`."""
    return 0.0 if UNDER_DEVKIT_KERNELS else elsewhere


# The versions of the official results in fixtures/reference and fixtures/knife-edge (v2.2's: fixtures/epdms,
# test_epdms_reference.py), all made on AVX-512 hosts with the SkylakeX kernels.
V1_VERSIONS = ("v1.0", "v1.1")


# How close the engine's continuous numbers (progress, scores, states) must come to the official v2.2 and
# two-stage ones: bit for bit under the official kernels.
CONTINUOUS_TOLERANCE = devkit_tolerance(1e-9)


def same_number(ours: float, official: float | None, tolerance: float = CONTINUOUS_TOLERANCE) -> bool:
    """Whether our number is the official one within `tolerance`, NaN equal to NaN (None in JSON)."""
    return math.isnan(ours) if official is None else abs(ours - official) <= tolerance


def same_values(ours: object, official: object, tolerance: float = CONTINUOUS_TOLERANCE) -> bool:
    """Whether nested lists or dicts of numbers, strings and None are the official ones: floats within
    `tolerance`, anything else (a bool, an int, a string) exactly."""
    if isinstance(ours, float) and isinstance(official, float):
        return same_number(ours, official, tolerance)
    if isinstance(ours, list | tuple) and isinstance(official, list | tuple):
        return len(ours) == len(official) and all(
            same_values(mine, theirs, tolerance) for mine, theirs in zip(ours, official, strict=True)
        )
    if isinstance(ours, dict) and isinstance(official, dict):
        return ours.keys() == official.keys() and all(
            same_values(ours[key], official[key], tolerance) for key in ours
        )
    return ours == official
