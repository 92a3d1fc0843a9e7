"""Two-stage EPDMS of one seed from its per-token results (docs/engine.md, "Two-stage EPDMS").

As `calculate_individual_mapping_scores` after `create_scene_aggregators`: per mapping entry, four weighted
averages of every score column, g1s1 over `orig`'s row, g1s2 over its now2 rows, g2s1 over `prev`'s row,
g2s2 over its prev2 rows (stage-one rows weigh 1, stage-two rows their pseudo-closed-loop weight; a
selection is taken in row order, as `isin` gives it, and each is sum(value * weight) / sum(weight) with
numpy); the entry's value is (g1s1 * g1s2 + g2s1 * g2s2) / 2. The summary rows are pandas means (NaN left
out) over [g1s1, g2s1] of every entry (stage one), over [g1s2, g2s2] (stage two) and over the entries'
values (combined); the reported EPDMS is the combined `score`. Entries whose `orig` and `prev` were both
not submitted are left out, as the official filter leaves them out.

Where the official script stops (a failed token, a token of an entry not submitted, a token in no entry,
an undefined two-frame comfort, a null mapping: its try block falls back and main() then crashes), this
scores what is defined and says why: a failed or missing token counts 0 in every column of its entry (as a
failed token counts 0 in a one-stage summary), a token in no entry keeps its row and enters no mean, an
undefined EC stays NaN and drops out of its means, and a null mapping leaves the summary undefined.
`official` is True exactly where the official script would have produced the same numbers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from scorer.evaluate import TokenResult
from scorer.geometry import BoolArray, FloatArray, IntArray
from scorer.human import is_synthetic
from scorer.metrics.aggregation import nan_skipping_mean
from scorer.two_stage.split import StageGroup, TwoStageSplit
from scorer.two_stage.sums import sums_by_group
from scorer.two_stage.weights import pseudo_closed_loop_weights
from scorer.versions import EPDMS_COLUMNS

SCORE_COLUMNS = EPDMS_COLUMNS  # the official `score_cols`: 8 subscores, two-frame comfort and score
GROUP_PARTS = ("original_stage_one", "original_stage_two", "previous_stage_one", "previous_stage_two")


@dataclass(frozen=True, eq=False)
class TwoStageToken:
    """A token's result as the aggregation reads it: its columns (`SCORE_COLUMNS`, EC included) and the two
    global points the weights compare (NaN where unknown)."""

    result: TokenResult
    start_point: tuple[float, float]  # the token's ego rear axle at t = 0 (the metric cache's)
    endpoint: tuple[float, float]  # its submitted last pose (`weights.global_endpoints`)


@dataclass(frozen=True)
class GroupScores:
    """One mapping entry: the four weighted averages (`GROUP_PARTS`), the entry's value and what it rests on."""

    original: str
    previous: str
    parts: dict[str, dict[str, float]]
    combined: dict[str, float]
    detail: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class TwoStageResult:
    """A seed's two-stage EPDMS: its rows in submission order, the weights, the groups and the three summaries
    (`stage_one`, `stage_two`, `combined`; NaN where undefined). `official` says the official script would
    have produced these numbers (its `pseudo_closed_loop_valid`); `notes` say why not where it would not."""

    rows: tuple[TokenResult, ...]
    weights: dict[str, float]  # every submitted token of a scored entry: 1.0 in stage one
    weight_detail: dict[str, dict[str, Any]]  # per stage-two token: how its weight came about
    groups: tuple[GroupScores, ...]
    stage_one: dict[str, float]
    stage_two: dict[str, float]
    combined: dict[str, float]
    official: bool
    notes: tuple[str, ...]

    @property
    def score(self) -> float:
        """Return the reported EPDMS: the combined score."""
        return self.combined["score"]


def _undefined_summary() -> dict[str, float]:
    return dict.fromkeys(SCORE_COLUMNS, math.nan)


def _values(row: TokenResult) -> list[float]:
    """Return a row's columns; a failed row counts 0 in each."""
    return [row.metrics.get(column, math.nan) if row.valid else 0.0 for column in SCORE_COLUMNS]


def _as_dicts(array: FloatArray) -> list[dict[str, float]]:
    """Return the columns (C, G) of G results as one dict per result."""
    return [dict(zip(SCORE_COLUMNS, column.tolist(), strict=True)) for column in array.T]


def aggregate_two_stage(tokens: Sequence[TwoStageToken], split: TwoStageSplit) -> TwoStageResult:
    """Return the two-stage EPDMS of one seed's per-token results, `tokens` in row order (stage one, then stage
    two, each in submission order), over the split's stage mapping."""
    rows = tuple(token.result for token in tokens)
    row_of = {row.token: index for index, row in enumerate(rows)}
    if len(row_of) != len(rows):
        raise ValueError("a token appears twice among one seed's results")
    if split.groups is None:
        note = "the split has no stage mapping (reactive_all_mapping is null): no group can be scored"
        return TwoStageResult(
            rows, {}, {}, (), _undefined_summary(), _undefined_summary(), _undefined_summary(), False, (note,)
        )
    groups = [group for group in split.groups if group.original in row_of or group.previous in row_of]
    grouped = {token: None for group in groups for token in group.tokens}  # mapping order
    # Tokens of a scored entry that were not submitted get rows of their own after the submitted ones.
    missing = [token for token in grouped if token not in row_of]
    for token in missing:
        row_of[token] = len(row_of)
    values = np.array([_values(row) for row in rows] + [[0.0] * len(SCORE_COLUMNS)] * len(missing))
    nowhere = np.full(2, math.nan)
    start_points = np.array([token.start_point for token in tokens] + [nowhere] * len(missing))
    endpoints = np.array([token.endpoint for token in tokens] + [nowhere] * len(missing))

    # Weight sets: orig against its now2 tokens, prev against its prev2 tokens, entry by entry.
    set_heads = [head for group in groups for head in (group.original, group.previous)]
    set_tokens = [tokens_ for group in groups for tokens_ in (group.now_tokens, group.previous_tokens)]
    synthetic = [token for members in set_tokens for token in members]
    sizes = np.array([len(members) for members in set_tokens], dtype=np.intp)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    sets = [np.arange(offsets[index], offsets[index + 1]) for index in range(len(set_tokens))]
    synthetic_rows = np.array([row_of[token] for token in synthetic], dtype=np.intp)
    weights = pseudo_closed_loop_weights(
        endpoints[[row_of[head] for head in set_heads]], start_points[synthetic_rows], sets
    )
    row_weight = np.ones(len(values))
    row_weight[synthetic_rows] = weights.weight

    # The four selections of each entry, in row order.
    selections: list[IntArray] = [
        np.sort(np.array([row_of[token] for token in members], dtype=np.intp))
        for group in groups
        for members in ((group.original,), group.now_tokens, (group.previous,), group.previous_tokens)
    ]
    weighted = sums_by_group(np.ascontiguousarray((values * row_weight[:, None]).T), selections)
    total_weight = sums_by_group(row_weight, selections)
    with np.errstate(invalid="ignore", divide="ignore"):
        averages = weighted / total_weight  # (C, 4 * entries)
    parts = averages.reshape(len(SCORE_COLUMNS), len(groups), 4)
    group_values = (parts[..., 0] * parts[..., 1] + parts[..., 2] * parts[..., 3]) / 2
    stage_one = nan_skipping_mean(np.ascontiguousarray(parts[..., [0, 2]].reshape(len(SCORE_COLUMNS), -1)))
    stage_two = nan_skipping_mean(np.ascontiguousarray(parts[..., [1, 3]].reshape(len(SCORE_COLUMNS), -1)))
    combined = nan_skipping_mean(np.ascontiguousarray(group_values))

    failed = {row.token for row in rows if not row.valid}
    undefined_comfort = {
        row.token
        for row in rows
        if row.valid and math.isnan(row.metrics.get("two_frame_extended_comfort", 0.0))
    }
    set_uniform = weights.uniform_fallback[offsets[:-1]] if len(synthetic) else np.zeros(0, dtype=bool)
    group_scores = tuple(
        GroupScores(
            original=group.original,
            previous=group.previous,
            parts=dict(zip(GROUP_PARTS, part_values, strict=True)),
            combined=combined_value,
            detail=_group_detail(
                group, failed, set(missing), undefined_comfort, set_uniform[2 * index : 2 * index + 2]
            ),
        )
        for index, (group, part_values, combined_value) in enumerate(
            zip(
                groups,
                (_as_dicts(parts[:, entry]) for entry in range(len(groups))),
                _as_dicts(group_values),
                strict=True,
            )
        )
    )
    notes = [f"token {token} failed: it counts 0 in its group" for token in grouped if token in failed]
    notes += [f"token {token} of a scored group was not submitted: it counts 0" for token in missing]
    notes += [
        f"token {row.token} is in no group of the mapping: its row is reported, no summary includes it"
        for row in rows
        if row.token not in grouped
    ]
    notes += [
        f"token {token}: two-frame extended comfort undefined, left out of the means"
        for token in sorted(undefined_comfort)
    ]
    if not groups:
        notes.append("no group of the mapping has a submitted stage-one token")
    head_of = dict(zip(synthetic, np.repeat(set_heads, sizes).tolist(), strict=True))
    weight_detail = {
        token: {
            "first_stage_token": head_of[token],
            "squared_distance": float(weights.squared_distance[index]),
            "exponent": float(weights.exponent[index]),
            "gaussian": float(weights.gaussian[index]),
            "weight_sum": float(weights.weight_sum[index]),
            "uniform_fallback": bool(weights.uniform_fallback[index]),
            "weight": float(weights.weight[index]),
            "n": int(weights.set_size[index]),
        }
        for index, token in enumerate(synthetic)
        if token not in missing
    }
    return TwoStageResult(
        rows=rows,
        weights={row.token: float(row_weight[row_of[row.token]]) for row in rows if row.token in grouped},
        weight_detail=weight_detail,
        groups=group_scores,
        stage_one=dict(zip(SCORE_COLUMNS, stage_one.tolist(), strict=True)),
        stage_two=dict(zip(SCORE_COLUMNS, stage_two.tolist(), strict=True)),
        combined=dict(zip(SCORE_COLUMNS, combined.tolist(), strict=True)),
        official=not notes,
        notes=tuple(notes),
    )


def _group_detail(
    group: StageGroup, failed: set[str], missing: set[str], undefined_comfort: set[str], uniform: BoolArray
) -> dict[str, Any]:
    """Return what a group's value rests on beyond the official premises, and its uniform weight sets."""
    detail: dict[str, Any] = {}
    for key, tokens in (
        ("failed", failed),
        ("not_submitted", missing),
        ("comfort_undefined", undefined_comfort),
    ):
        found = [token for token in group.tokens if token in tokens]
        if found:
            detail[key] = found
    uniform_sets = [head for head, flag in zip(("original", "previous"), uniform, strict=True) if flag]
    if uniform_sets:
        detail["uniform_weights"] = uniform_sets  # official behaviour: no synthetic start near the endpoint
    return detail


def stage_of(row: TokenResult) -> int | None:
    """Return the stage a row's columns belong to in the official CSV: 1 for a logged frame, 2 for a synthetic
    one (NAVSIM's frame type), None for a failed row (the official failed row has no frame type)."""
    if not row.valid:
        return None
    return 2 if is_synthetic(row.token) else 1
