"""The pseudo-closed-loop weights of the stage-two tokens (docs/engine.md, "Two-stage EPDMS").

As `calculate_pseudo_closed_loop_weights`: a stage-one token's synthetic successors are weighted by how close
each one's start (its cached ego rear axle) lies to where the token's submitted plan ends, in the global
frame: w = exp(-d² / (2 * 0.1)), normalised over the set; when the Gaussians sum to nothing (numpy's
`isclose(sum, 0)`, i.e. at most 1e-8: no start within about 1.92 m) or to NaN, every weight is 1/n.

Bit for bit: d² is dx ** 2 + dy ** 2 of Python floats, and a float's `** 2` is the C library's pow(x, 2),
which is not always x * x (5 of the 400 reference distances differ in the last bit): numpy's `float_power`
calls that pow element by element, where `x ** 2` and `power` on arrays square or take a SIMD path. The
exponential is numpy's on AVX-512 (SVML's, replayed elsewhere: `svml_exp.exp_avx512`; it differs from the C
library's in the last bit for a few percent of arguments);
the set's sum is numpy's over the set in mapping order (`sums.sums_by_group`). The endpoint is nuPlan's `relative_to_absolute_poses` of the submitted last
pose: (cos h0 * x + (-sin h0) * y) + x0 and (sin h0 * x + cos h0 * y) + y0, without fused multiply-adds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from scorer.geometry import BoolArray, FloatArray, IntArray
from scorer.svml_exp import exp_avx512
from scorer.two_stage.sums import sums_by_group

GAUSSIAN_DENOMINATOR = 2 * 0.1  # 2 sigma² with the official sigma² = 0.1 m²
UNIFORM_BELOW = 1e-8  # numpy's isclose(sum, 0.0) tolerance: a sum up to this falls back to 1/n


class WeightSets(NamedTuple):
    """Weights of stage-two tokens (T,) in sets; each array per token, the set's values repeated."""

    squared_distance: FloatArray  # m², the set's endpoint to the token's start point
    exponent: FloatArray  # -d² / 0.2
    gaussian: FloatArray  # numpy's exp of it
    weight_sum: FloatArray  # the set's sum of Gaussians
    uniform_fallback: BoolArray  # the set's sum is at most 1e-8 or NaN: every weight 1/n
    weight: FloatArray
    set_size: IntArray


def global_endpoints(poses: FloatArray, ego_poses: FloatArray) -> FloatArray:
    """Return (N, 2): the last of each token's submitted poses (N, 8, 3) in the global frame of its ego rear
    axle (N, 3) x0, y0, h0, as nuPlan's 3x3 matrix product evaluates it."""
    x, y = poses[:, -1, 0], poses[:, -1, 1]
    x0, y0, h0 = ego_poses[:, 0], ego_poses[:, 1], ego_poses[:, 2]
    cos, sin = np.cos(h0), np.sin(h0)
    return np.stack([(cos * x + (-sin) * y) + x0, (sin * x + cos * y) + y0], axis=-1)


def pseudo_closed_loop_weights(
    endpoints: FloatArray, start_points: FloatArray, sets: Sequence[IntArray]
) -> WeightSets:
    """Return the weights of T stage-two tokens with start points (T, 2) in weight sets: set s holds the tokens
    `sets[s]` (in mapping order) and is weighted against `endpoints[s]` (S, 2). Every token is in one set.
    NaN in an endpoint or a start point makes its set uniform, as a NaN sum does officially."""
    set_of = np.empty(len(start_points), dtype=np.intp)
    for index, members in enumerate(sets):
        set_of[members] = index
    difference = endpoints[set_of] - start_points
    squared = np.float_power(difference, 2.0)
    squared_distance = squared[:, 0] + squared[:, 1]
    exponent = -squared_distance / GAUSSIAN_DENOMINATOR
    gaussian = exp_avx512(exponent)
    set_sum = sums_by_group(gaussian, sets)
    set_size = np.array([len(members) for members in sets], dtype=np.intp)
    uniform = (set_sum <= UNIFORM_BELOW) | np.isnan(set_sum)
    with np.errstate(invalid="ignore", divide="ignore"):  # a uniform set's own division is not used
        weight = np.where(uniform[set_of], 1 / set_size[set_of], gaussian / set_sum[set_of])
    return WeightSets(
        squared_distance=squared_distance,
        exponent=exponent,
        gaussian=gaussian,
        weight_sum=set_sum[set_of],
        uniform_fallback=uniform[set_of],
        weight=weight,
        set_size=set_size[set_of],
    )
