"""Why v2.2's two-frame extended comfort (EC) is undefined on a row, in words a team can act on.

EC compares a token's simulated plan with the plan of the frame of its log just before it, so it exists only
where `scorer.evaluate.join_two_frame_comfort` paired the row: one-stage, with the latest frame of its log that
starts at most 0.55 s earlier in the same run (`adjacent_pairs`); two-stage, with its partner of the split's
stage mapping. Where the devkit pairs two frames and then fails on them, the row's detail already says why
(`detail["two_frame_extended_comfort"]["undefined"]`); every other undefined EC is a row that was never
paired, which the detail does not record: this module names that case too. An undefined EC drops out of the
row's score with its weight (/14 instead of /16), as in the official code.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from scorer.human import is_synthetic
from scorer.metrics.two_frame_comfort import ADJACENT_GAP_S

SYNTHETIC = "a synthetic scene (17-character token) has no logged frame before it to compare its plan with"
UNPAIRED = (
    f"no frame of its log starts within {ADJACENT_GAP_S:g} s before it in the split (it is the first of its log"
    " here, or the one before is further back), so there is no earlier plan to compare with"
)
# An entry's mean over a subset is undefined when no token of it has EC.
NO_TOKEN_PAIRED = (
    "undefined on every token of this subset: no token has the frame of its log 0.5 s earlier in the split, so"
    " there is no earlier plan to compare with"
)


def ec_undefined_reason(token: str, detail: Mapping[str, Any]) -> str:
    """Return why EC is undefined on the row of `token` whose detail is `detail` (call it where EC is NaN)."""
    pairing = detail.get("two_frame_extended_comfort", {})
    if "undefined" in pairing:
        return str(pairing["undefined"])
    if is_synthetic(token) and not pairing:
        return SYNTHETIC
    return UNPAIRED
