"""`vrcp14pd`, the AVX-512 reciprocal estimate that SVML's functions start their divisions from, on every host.

Not a correctly rounded reciprocal but a table of 2^16 significands indexed by the top 16 bits of the
divisor's (Intel's reference implementation, which Bochs reproduces; read off an AVX-512 CPU), with the
exponent negated; an exact power of two gets its exact reciprocal. SVML refines it with Newton steps whose
last bits depend on it: with the correctly rounded reciprocal instead, 0.3 % of SVML's tan results and a few
in a million of its arctan2 results would differ (`scorer.svml_tan`, `scorer.geometry`).
"""

from __future__ import annotations

import binascii
import math
import struct
import zlib
from functools import cache
from typing import Any

import numpy as np
import numpy.typing as npt

# The significands: entry i, for divisors 1 + i / 2^16 (+ anything below), is 2^-17 (2^16 + m_i) in (0.5, 1),
# m_i falling from 65532; stored as the steps m_{i-1} - m_i (0, 1, 2 or 4, from m_{-1} = 65536), zlib-compressed.
_RCP14_STEPS = (
    "eNrtl+tyAyEIhdHp+z9z/7TpXtRVi67Cl028wIEDh0mm/YrXV4hPL18I2kUQu4gw82iBwVg7CMb8q7algRRnsjgkHg6Uz3GHhULd"
    "FoqsY5ZPuRUfg1Df3QNFqFBx0oQ6JkMl5r8oWbjcng0hDjfYoEA55r8wxeHatHQF7RXpoEXEYf7HbdxhOAGtIBqttBL8We5PwdXv"
    "HJI00AbC0UaPM/HUmWpxhNoMRRMLQ7z4Qvoe/gXbN9p8g8jjvMHDjcXpggpuFzncsseyVy/GByXKMP9lKOVoqH33xCxKY6gVaFCs"
    "PSYR22/4V/DK2cw2hkzeG/s5Hz/Ppq6gbpMZNhpBtrXYLrYboPLSAJ1AsW01FI6McynkZCsvwOzBUMX5/H+32+rD7KlXzEhwXeP1"
    "d+Dkr9g0EDsAKY75Gyzu+IfAbX82OELSKqIYRH68ydMI487ZaQi5TGY/wG638lUN+wrp8gVCiioDsfECSod2WAOJd0iMms4TZzKH"
    "FkIlOMnnJ0dF5/P3/kIu5u/4JQvBSW4sOSrulVwaU0p4K2C9RIhHCxsySwYr5VRe3OjA/E2748PvwoSzUAKdU8I7tPF8T5xsOx23"
    "jhNdCv8ISK3DHpJWEcVRq5J0lbYpGF+FIDvzfwFzcqx/oVwEpVz1CjMrZq9mJPAy6AtCUncZCyK92fQouPqAkjAJVYsfGKowf6uw"
    "lLvvoJFDKIjuKGhaQX/3G6Bo9B2GRszfRFgWN+vzKjkFMH/vBSSsz6auoG7TnqmRjUb2YWuwtDvGQJ2WDB0KqeWId38uU4lB0e6x"
    "CopHwnfSSc51Oj0CGqCOyVCJ+S9KljUZt7psGimY/887FoRRfM/ggGZdGhRbdTC1SE0U6ZZJhyTO0+XxD4ZWvFsKlGP+y1LEmztx"
    "LHv1Yl6g3KRMKFFmSEzMIJv294Lfr4DyEdBK+VzcXRCC+ScsFUtX0F6RDlpEHOctXkxpYCHH5gF2OyMAKWqsBd/MM+SoAPl88qNF"
    "dRuW2G+xSMr81bekVerMYj2aBpHHeIOSARQOPTF9B0NMtIJo6zElfwE0jsrpnJeJsMx/SDrJZb79hdBzsRpFk0hjI0ry/we4MHjr"
    "FwMClL//WaHazUppnJeIuMx/WBoJNY8WaCqZ5bIRkvmrgOq+/63PPkl3qpWkCKD9fAM68QAQ"
)


def decoded_steps(text: str) -> npt.NDArray[np.uint8]:
    """Return the steps between a table's significands, stored as base64 of their zlib-compressed bytes (decoded
    by binascii, as base64.b64decode would, without importing the base64 module at every start-up)."""
    return np.frombuffer(zlib.decompress(binascii.a2b_base64(text)), dtype=np.uint8)


@cache
def significands() -> npt.NDArray[np.floating[Any]]:
    """Return the table (decoded once, when first needed: on AVX-512 hosts numpy's own SVML runs instead)."""
    steps = decoded_steps(_RCP14_STEPS)
    return (2**16 + (2**16 - np.cumsum(steps, dtype=np.int64))) * 2.0**-17


@cache
def _significand_floats() -> list[float]:
    return significands().tolist()


_FRACTION_BITS = (1 << 52) - 1
_DOUBLE, _DOUBLE_BITS = struct.Struct("<d"), struct.Struct("<q")


def rcp14(divisor: npt.NDArray[np.floating[Any]]) -> npt.NDArray[np.floating[Any]]:
    """Return `vrcp14pd` of finite, non-zero, normal divisors (other lanes get values to be discarded)."""
    bits = divisor.view(np.int64)
    exact = (bits & _FRACTION_BITS) == 0
    significand = np.where(exact, 1.0, significands()[(bits >> 36) & 0xFFFF])
    with np.errstate(invalid="ignore"):
        _, exponent = np.frexp(divisor)  # divisor = m 2^exponent, m in [0.5, 1)
    return np.copysign(np.ldexp(significand, 1 - exponent), divisor)


def rcp14_float(divisor: float) -> float:
    """`rcp14` of one finite, non-zero, normal Python float."""
    bits = _DOUBLE_BITS.unpack(_DOUBLE.pack(divisor))[0]
    significand = 1.0 if bits & _FRACTION_BITS == 0 else _significand_floats()[(bits >> 36) & 0xFFFF]
    return math.copysign(math.ldexp(significand, 1 - math.frexp(divisor)[1]), divisor)
