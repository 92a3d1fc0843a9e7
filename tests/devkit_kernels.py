"""How close a number must come to the official devkit's: exactly under the official results' OpenBLAS
kernels (what `scorer.blas` selects where the CPU runs them), else within the last bits `pinv` moves."""

from __future__ import annotations

from scorer.blas import DEVKIT_KERNELS, blas_kernels

UNDER_DEVKIT_KERNELS = blas_kernels() == (DEVKIT_KERNELS,)


def devkit_tolerance(elsewhere: float) -> float:
    """Return 0 under the devkit's kernels, else `elsewhere`."""
    return 0.0 if UNDER_DEVKIT_KERNELS else elsewhere


# The versions of the official results in fixtures/reference and fixtures/knife-edge (v2.2's: fixtures/epdms,
# test_epdms_reference.py), all made on AVX-512 hosts with the SkylakeX kernels.
V1_VERSIONS = ("v1.0", "v1.1")
