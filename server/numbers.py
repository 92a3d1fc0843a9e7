"""How every page, the command line and the reports write a score: one unit, one rounding, one function.

A score or subscore is stored as a float in [0, 1] and shown in percent with one decimal: 100 × the stored float
(one IEEE multiplication), rounded on that product's exact value, halves away from zero; an undefined value
is "–". That is JavaScript's `toFixed(1)`, so `percent` here and `pct` in web/static/common.js write the same
figure for the same float (95.25 is 95.3 in both). The exports keep the stored floats themselves, unrounded.
"""

from __future__ import annotations

import math
from decimal import ROUND_HALF_UP, Decimal

UNDEFINED = "–"
ONE_DECIMAL = Decimal("0.1")


def percent(value: float | None) -> str:
    """Return a fraction in percent with one decimal ("95.3"), "–" when undefined (None, NaN or infinite)."""
    if value is None or not math.isfinite(value):
        return UNDEFINED
    # Decimal(float) is the float's exact value: rounding it is rounding the product, as toFixed does.
    text = str(Decimal(100 * value).quantize(ONE_DECIMAL, rounding=ROUND_HALF_UP))
    return "0.0" if text == "-0.0" else text


def counted(count: int, singular: str, plural: str | None = None) -> str:
    """Return "1 entry", "2 entries": a count with its noun in the right number."""
    return f"{count} {singular if count == 1 else plural or singular + 's'}"
