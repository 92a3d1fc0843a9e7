"""How every page, the command line and the reports write a score: one unit, one rounding, one function.

A score or subscore is stored as a float in [0, 1] and shown in percent with one decimal: 100 × the stored float
(one IEEE multiplication), rounded on that product's exact value, halves away from zero; an undefined value
is "–". That is JavaScript's `toFixed(1)`, so `percent` here and `pct` in web/static/common.js write the same
figure for the same float (95.25 is 95.3 in both). The exports keep the stored floats themselves, unrounded.
"""

from __future__ import annotations

import math

UNDEFINED = "–"


def percent(value: float | None) -> str:
    """Return a fraction in percent with one decimal ("95.3"), "–" when undefined (None, NaN or infinite)."""
    if value is None or not math.isfinite(value):
        return UNDEFINED
    # The product's exact value as a ratio of integers, rounded to tenths as toFixed rounds it (in integers: the
    # decimal module is most of a millisecond of every `navsim-lb score`).
    numerator, denominator = (100 * value).as_integer_ratio()
    tenths, remainder = divmod(abs(numerator) * 10, denominator)
    tenths += 2 * remainder >= denominator  # halves away from zero
    sign = "-" if numerator < 0 and tenths else ""  # no "-0.0"
    return f"{sign}{tenths // 10}.{tenths % 10}"


def counted(count: int, singular: str, plural: str | None = None) -> str:
    """Return "1 entry", "2 entries": a count with its noun in the right number."""
    return f"{count} {singular if count == 1 else plural or singular + 's'}"
