"""Where the official script crashes (spec: a failed token, a token in no group, a group's token not submitted,
an undefined two-frame comfort, a null mapping), the aggregation scores what is defined and says why; the
groups the case does not touch keep their official values bit for bit."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from two_stage_reference import SPLIT, aggregation_input, official_summary

from scorer.evaluate import TokenResult
from scorer.two_stage.aggregate import SCORE_COLUMNS, TwoStageResult, TwoStageToken, aggregate_two_stage
from scorer.two_stage.result_csv import two_stage_csv
from scorer.two_stage.split import TwoStageSplit

FAMILY = "human"
assert SPLIT.groups is not None
GROUPS = SPLIT.groups


def _official_groups_unchanged(result: TwoStageResult, except_index: int) -> None:
    expected = official_summary(FAMILY)["groups"]
    for index, (group, official) in enumerate(zip(result.groups, expected, strict=True)):
        if index != except_index:
            assert group.combined["score"] == official["combined"], index


def _with(tokens: list[TwoStageToken], token: str, **changes: object) -> list[TwoStageToken]:
    return [
        replace(item, result=replace(item.result, **changes)) if item.result.token == token else item
        for item in tokens
    ]


def test_a_failed_token_counts_zero_in_its_group_only() -> None:
    failed = GROUPS[0].now_tokens[2]
    tokens = _with(aggregation_input(FAMILY), failed, valid=False, metrics={}, error="scoring failed")
    result = aggregate_two_stage(tokens, SPLIT)
    assert not result.official
    assert result.notes == (f"token {failed} failed: it counts 0 in its group",)
    assert result.groups[0].detail["failed"] == [failed]
    weights = {token: result.weights[token] for token in GROUPS[0].now_tokens}
    by_token = {item.result.token: item.result for item in tokens}
    expected = sum(weights[t] * (by_token[t].metrics["score"] if t != failed else 0.0) for t in weights)
    assert math.isclose(
        result.groups[0].parts["original_stage_two"]["score"], expected / sum(weights.values())
    )
    _official_groups_unchanged(result, except_index=0)
    assert not math.isnan(result.score)
    line = two_stage_csv(result).splitlines()[1 + [item.result.token for item in tokens].index(failed)]
    assert line.endswith(f",{failed},False" + "," * 19)  # no frame type: neither stage's columns, no score


def test_a_token_in_no_group_keeps_its_row_and_enters_no_mean() -> None:
    extra = TwoStageToken(
        TokenResult("f" * 16, None, True, dict.fromkeys(SCORE_COLUMNS, 0.5)), (0.0, 0.0), (1.0, 1.0)
    )
    tokens = aggregation_input(FAMILY)
    result = aggregate_two_stage([*tokens[:80], extra, *tokens[80:]], SPLIT)
    assert result.notes == (
        f"token {'f' * 16} is in no group of the mapping: its row is reported, no summary includes it",
    )
    assert result.combined == official_summary(FAMILY)["summary_rows_exact"]["combined"]
    assert f"80,{'f' * 16},True,0.5," in two_stage_csv(result)


def test_a_token_not_submitted_counts_zero_and_its_weight_set_falls_back_to_uniform() -> None:
    missing = GROUPS[3].previous_tokens[1]
    tokens = [item for item in aggregation_input(FAMILY) if item.result.token != missing]
    result = aggregate_two_stage(tokens, SPLIT)
    assert result.notes == (f"token {missing} of a scored group was not submitted: it counts 0",)
    assert result.groups[3].detail == {"not_submitted": [missing], "uniform_weights": ["previous"]}
    assert [result.weights[token] for token in GROUPS[3].previous_tokens if token != missing] == [0.2] * 4
    _official_groups_unchanged(result, except_index=3)


def test_a_group_without_submitted_stage_one_tokens_is_left_out_as_officially() -> None:
    left_out = set(GROUPS[5].tokens)
    tokens = [item for item in aggregation_input(FAMILY) if item.result.token not in left_out]
    result = aggregate_two_stage(tokens, SPLIT)
    assert len(result.groups) == 39 and GROUPS[5].original not in {group.original for group in result.groups}
    assert result.official  # the official filter drops such an entry and scores the rest


def test_an_undefined_comfort_drops_out_of_its_means_only() -> None:
    """E.g. two frames of an entry with equal start times: the official EC asserts, the run falls back."""
    original = GROUPS[7].original
    tokens = aggregation_input(FAMILY)
    metrics = dict(next(item.result.metrics for item in tokens if item.result.token == original))
    metrics["two_frame_extended_comfort"] = math.nan
    result = aggregate_two_stage(_with(tokens, original, metrics=metrics), SPLIT)
    assert result.groups[7].detail == {"comfort_undefined": [original]}
    assert math.isnan(result.groups[7].parts["original_stage_one"]["two_frame_extended_comfort"])
    official = official_summary(FAMILY)["summary_rows_exact"]
    assert (
        result.stage_one["two_frame_extended_comfort"] != official["stage_one"]["two_frame_extended_comfort"]
    )
    assert result.stage_one["score"] == official["stage_one"]["score"]  # the row's score is unchanged here
    assert not result.official


def test_a_null_mapping_keeps_the_rows_and_leaves_the_summary_undefined() -> None:
    split = TwoStageSplit(None, SPLIT.stage_one_tokens, SPLIT.stage_two_tokens)
    result = aggregate_two_stage(aggregation_input(FAMILY), split)
    assert result.groups == () and math.isnan(result.score) and not result.official
    assert "reactive_all_mapping is null" in result.notes[0]
    text = two_stage_csv(result)
    assert len(text.splitlines()) == 1 + 480 + 3
    assert text.splitlines()[-1] == "482,extended_pdm_score_combined,False" + "," * 19
    assert np.isnan(list(result.stage_two.values())).all()
