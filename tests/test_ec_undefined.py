"""Why EC is undefined on a row: the engine's own reason where it paired and failed, else never paired."""

from __future__ import annotations

from scorer.ec_undefined import SYNTHETIC, UNPAIRED, ec_undefined_reason


def test_the_reason_is_the_engine_s_where_it_gave_one_else_the_row_was_never_paired() -> None:
    failed = {"two_frame_extended_comfort": {"previous_token": "p", "undefined": "frames 0.0 s apart"}}
    assert ec_undefined_reason("a" * 16, failed) == "frames 0.0 s apart"
    assert ec_undefined_reason("a" * 16, {}) == UNPAIRED
    assert ec_undefined_reason("a" * 16, {"human_filter": {"overridden": []}}) == UNPAIRED
    assert ec_undefined_reason("s" * 17, {}) == SYNTHETIC
    # A synthetic token the two-stage mapping paired, and whose partner failed, says so.
    paired = {
        "two_frame_extended_comfort": {"current_token": "c", "undefined": "its partner c was not scored"}
    }
    assert ec_undefined_reason("s" * 17, paired) == "its partner c was not scored"
