"""Sums and means in the order the official aggregation adds its floats (docs/engine.md, "Two-stage EPDMS").

Every sum of the two-stage aggregation (a weight set's Gaussians, a group's weighted scores and weights, the
summary means over groups) is numpy's (or pandas', which calls numpy) sum of a contiguous 1-D float64 array:
sequential below 8 values, pairwise above (eight partial sums of stride 8, combined as a tree, the rest added
in order, halves beyond 128). Which values go together and in what order therefore decides the last bits.
Rather than transcribe that order, the sums here hand numpy a C-contiguous (groups, n) array per group size
n and sum over its last axis, which runs the same pairwise loop on each row; padding the groups to one size
would change the pairing.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from scorer.geometry import FloatArray, IntArray


def sums_by_group(values: FloatArray, members: Sequence[IntArray]) -> FloatArray:
    """Return (..., G): for each group g the sum of `values[..., members[g]]` in member order, as numpy sums a
    contiguous array of those values (0.0 for an empty group)."""
    sums = np.zeros((*values.shape[:-1], len(members)))
    sizes = np.array([len(member) for member in members], dtype=np.int64)
    for size in np.unique(sizes[sizes > 0]):
        groups = np.flatnonzero(sizes == size)
        index = np.stack([members[int(group)] for group in groups])  # (groups, size)
        sums[..., groups] = np.ascontiguousarray(values[..., index]).sum(axis=-1)
    return sums
