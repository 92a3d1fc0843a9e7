"""`vrsqrt14pd`, the AVX-512 reciprocal square root estimate that SVML's arccos starts its square root from.

Like `vrcp14pd` (`scorer.rcp14`), not a correctly rounded value but a table: 2^15 significands for each parity
of the exponent, indexed by the top 15 bits of the argument's significand, the exponent halved; an exact even
power of two gets its exact reciprocal square root. Read off an AVX-512 CPU (every one of the 2^16 entries,
and checked on 2e6 random arguments over 265 binades). SVML refines it with polynomial corrections whose last
bits can depend on it (`scorer.svml_acos`).
"""

from __future__ import annotations

from functools import cache
from typing import Any

import numpy as np
import numpy.typing as npt

from scorer.rcp14 import decoded_steps

# The significands: entry p 2^15 + i, for arguments 2^p (1 + i / 2^15 + anything below), is 2^-17 s_i in
# (1/2, 1], s falling from 2^17; stored as the steps s_{i-1} - s_i (0 to 6, from s_{-1} = 2^17),
# zlib-compressed.
_RSQRT14_STEPS = (
    "eNrtnOtu5CAMhU262vd/5JU6OzMhQAIkgMFfOg34wvHxsaZS//B3Ozxuiz1xb1FyZ2DN3ABm/qqAne8pMZudsUEGyZn/yDM/b8Pt"
    "NylXvqUqHWqIDLVogns7i5aaM4aLoBrzV1rEvXZu238MWWYbRwbm/3pF9tGlJjIUm46gRUcXCf93+5+IqyJFYxK0ERLanuO1es74"
    "NsvPYbTg8EyMkq+TkN10RGH+a6X/Lp/PmdXHQQlTJVBubIm9HdvdNoBCHqDUEpGvcxds5WoI7WgE2Wik1CVf62qTndgYY21CyM38"
    "+2N47/h2zWR7HZOMPN/33mLpv6AB8x+5iM9mtws3vWMUXr8waowtLC4MX1nZiUAiA5CqOYsLns3Fn5S/+IA+IIuVaQHxot//+mdz"
    "XZ5toSpLNYNk0zVT+P1vmg74YuCoqH9EGaeFxGaJKMH8RyZux+Bt42E4CtEEhZpiBz5rO8OtI4L5+cvBWboCMBIA8Zj/jVXe9sny"
    "RMbARMghMeQSieKdkjBc9C5M73cIYsgMschbwmjaznc+lzQ3PAoy/2ng863C9J611qGGyMy/+eGfjyHHaIExUyrEkRHiXyPI7f1r"
    "mwDyM/+Rv7WmLhjV5IBh/lph5OBO5hcv/Q6ZIUtB1Hn47B/vYmBvxdnBiQbMf6Rzi1wKHL8quLlXCQ2koGk7Umxcm2y6EWRj/of7"
    "glOuB1KBWBAC2WaHuHqTtGwSChmfv/ONLeVoFOleUHOElhGjc0Qc998CyfwtQ6ZcQzLUEKFdBFm/3U63nCYfcdM8UEXU5ajK+YFS"
    "/zggi5VpAfFuHpB4jPsvKcT87RSK7KRLbFhhlaQojBojYtFbwnJuEuuSs04RiDB/XUS+9/9bftM8EtD82WtQGFaQhlVT0sFFJJdW"
    "mfvO2fXpIDjzH3lW6i4mmiwAMyjDLHr91/WVYNWuOaFpBNnsNCI3rxUKlqfxKEJDFGlWS8Kgt7ttANULCnmYf7mRDF1+WmarIkOj"
    "yLJqoxLY6czyiH7AmbkDiBj3IzF/9rbXGUqiDCVblExg4DTsRANDTjmmJE4WvQycpEXEmf+kHP4WuM6O/hXNsIYk0l47jtGzJTdP"
    "xQJZJIXs5eL/D5C3qTljvhKtIJrWSh8rY1uWPWwLTYSFZjaLwMTRxYEizH+kw8UonbC9H2wCKrSBcLRRAXp6sPZnHlBxgDJ/u6D/"
    "ABaxABA="
)


@cache
def significands() -> npt.NDArray[np.floating[Any]]:
    """Return the table (decoded once, when first needed: on AVX-512 hosts numpy's own SVML runs instead)."""
    return (2**17 - np.cumsum(decoded_steps(_RSQRT14_STEPS), dtype=np.int64)) * 2.0**-17


_FRACTION_BITS = (1 << 52) - 1


def rsqrt14(argument: npt.NDArray[np.floating[Any]]) -> npt.NDArray[np.floating[Any]]:
    """Return `vrsqrt14pd` of finite, positive, normal arguments (other lanes get values to be discarded)."""
    with np.errstate(invalid="ignore"):
        mantissa, exponent = np.frexp(argument)  # argument = (2 mantissa) 2^(exponent - 1)
    unbiased = exponent - 1
    parity = unbiased & 1
    fraction = (2 * mantissa).view(np.int64) & _FRACTION_BITS
    estimate = np.ldexp(significands()[parity * 2**15 + (fraction >> 37)], -(unbiased - parity) // 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((fraction == 0) & (parity == 0), 1 / np.sqrt(argument), estimate)
