"""AVX-512's embedded roundings toward zero and downward, from float64 operations that round to nearest.

SVML's pow and exp round a few operations with an instruction's own rounding mode (`{rz-sae}`, `{rd-sae}`)
instead of to nearest; their replays (`scorer.svml_pow`, `scorer.svml_exp`) need the same results on any
host. Each operation is computed to nearest with its exact error (Knuth's two-sum, the exact FMA of
`geometry._exact_multiply_add`), and moved one ulp where the exact value lies on the other side: toward
zero when the error's sign is not the result's, down when the error is negative. Exact for operands whose
products do not underflow (|a|, |b| >= 1e-100 or zero), like the FMA emulation it builds on.
"""

from __future__ import annotations

import numpy as np

from scorer.geometry import FloatArray, _exact_multiply_add, _fused_multiply_add, _two_sum


def _toward_zero(nearest: FloatArray, error_sign: FloatArray) -> FloatArray:
    """Return the value toward zero of `nearest`, given the sign of (exact - nearest)."""
    return np.where((error_sign != 0) & (error_sign != np.sign(nearest)), np.nextafter(nearest, 0.0), nearest)


def multiply_toward_zero(a: FloatArray, b: FloatArray) -> FloatArray:
    """Return a * b rounded toward zero (`vmulpd {rz-sae}`)."""
    nearest = a * b
    return _toward_zero(nearest, np.sign(_fused_multiply_add(a, b, -nearest)))


def fused_multiply_add_toward_zero(a: FloatArray, b: FloatArray, c: FloatArray) -> FloatArray:
    """Return a * b + c rounded once toward zero (`vfmadd...pd {rz-sae}`).

    The exact value is high + tail + error (`_exact_multiply_add`); its distance from the nearest result is
    (high - nearest) + tail + error, where high - nearest is exact (the two are within an ulp) and the sum
    with the tail either is zero (then the error decides) or outweighs the error, which is below half an ulp
    of the tail."""
    nearest = _fused_multiply_add(a, b, c)
    high, tail, error = _exact_multiply_add(a, b, c, None)
    distance = (high - nearest) + tail
    return _toward_zero(nearest, np.where(distance != 0, np.sign(distance), np.sign(error)))


def add_toward_zero(a: FloatArray, b: FloatArray) -> FloatArray:
    """Return a + b rounded toward zero (`vaddpd {rz-sae}`)."""
    total, error = _two_sum(a, b)
    return _toward_zero(total, np.sign(error))


def add_downward(a: FloatArray, b: FloatArray) -> FloatArray:
    """Return a + b rounded toward minus infinity (`vaddpd {rd-sae}`)."""
    total, error = _two_sum(a, b)
    return np.where(error < 0, np.nextafter(total, -np.inf), total)
