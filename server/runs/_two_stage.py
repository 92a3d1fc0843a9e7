"""A two-stage run's rows and its aggregation (NAVSIM v2.2's two-stage EPDMS, docs/engine.md "Two-stage EPDMS").

A chunk writes each token's row as any version's, with `detail["two_stage"]`: its stage, its place in the
seed's submission (the official row order, which decides the last bits of the sums), its start point and its
submitted endpoint (what the weights compare). Floats travel as the database and JSON store them, exactly
(double precision, shortest repr), so the end of the run rebuilds each seed's `TwoStageToken`s from the rows
and runs `scorer.two_stage.aggregate.aggregate_two_stage` on them: the numbers `navsim-lb score` gives the
same split and submission, bit for bit. It then writes each row's weight into its detail, per seed a Result
(its combined row; `two_stage` the stage summaries, the groups with their reasons, the notes), and the entry's
Summary: means, std and max of the combined score over seeds and a bootstrap interval over groups (their
seed-averaged values: the combined score is a mean over groups, as the one-stage score is over tokens).
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from scorer.metrics.aggregation import defined_mean
from scorer.versions import get_version
from server.models import Submission, Summary, TokenResultRow
from server.runs._aggregate import bootstrap_cis, seed_result, seed_summary, stored_value
from server.services.splits import ALL_SUBSET, stage_mapping

if TYPE_CHECKING:
    from scorer.evaluate import TokenResult
    from scorer.two_stage.aggregate import TwoStageResult, TwoStageToken
    from scorer.two_stage.split import TwoStageSplit

DETAIL_KEY = "two_stage"
MAX_KEPT_NOTES = 200  # a navhard-size run's notes stay readable; the count says how many there were


def _point(values: Sequence[float]) -> list[float] | None:
    """Return a point as JSON holds it: None where unknown (JSON has no NaN)."""
    return None if any(math.isnan(value) for value in values) else [float(value) for value in values]


def _unpoint(values: Sequence[float] | None) -> tuple[float, float]:
    return (math.nan, math.nan) if values is None else (float(values[0]), float(values[1]))


def json_safe(value: Any) -> Any:
    """Return `value` with every NaN as None, for a JSON column (PostgreSQL's JSON refuses NaN)."""
    if isinstance(value, float):
        return None if math.isnan(value) else value
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(item) for item in value]
    return value


def stage_rows(
    scored: Mapping[int | None, Sequence[TwoStageToken]], order: Mapping[int | None, Sequence[str]]
) -> list[TokenResult]:
    """Return the rows a chunk writes of its two-stage results, per seed: each result with its stage, its row in
    the seed's submission (`order`: the seed's tokens in submission order), start point and endpoint."""
    from dataclasses import replace

    from scorer.two_stage.aggregate import stage_of

    rows = []
    for seed, tokens in scored.items():
        row_of = {token: index for index, token in enumerate(order[seed])}
        for item in tokens:
            result = item.result
            block = {
                "stage": stage_of(replace(result, valid=True)),
                "row": row_of[result.token],
                "start_point": _point(item.start_point),
                "endpoint": _point(item.endpoint),
            }
            rows.append(replace(result, detail={**result.detail, DETAIL_KEY: block}))
    return rows


def _seed_tokens(session: Session, submission: Submission, version: str) -> dict[int, list[tuple[int, Any]]]:
    """Return seed -> (row id, TwoStageToken) of the current run's rows of `version`, in submission order."""
    from scorer.evaluate import TokenResult
    from scorer.two_stage.aggregate import SCORE_COLUMNS, TwoStageToken

    columns = [getattr(TokenResultRow, column) for column in SCORE_COLUMNS]
    query = select(
        TokenResultRow.id,
        TokenResultRow.seed,
        TokenResultRow.token,
        TokenResultRow.valid,
        TokenResultRow.error,
        TokenResultRow.detail,
        *columns,
    ).where(
        TokenResultRow.submission_id == submission.id,
        TokenResultRow.run == submission.run,
        TokenResultRow.metric_version == version,
    )
    by_seed: dict[int, list[tuple[int, int, Any]]] = defaultdict(list)
    for row_id, seed, token, valid, error, detail, *values in session.execute(query).all():
        detail = dict(detail or {})
        block = detail.get(DETAIL_KEY, {})
        metrics = {
            column: math.nan if value is None else float(value)
            for column, value in zip(SCORE_COLUMNS, values, strict=True)
        }
        result = TokenResult(token, seed, valid, metrics if valid else {}, error, detail)
        item = TwoStageToken(result, _unpoint(block.get("start_point")), _unpoint(block.get("endpoint")))
        by_seed[seed].append((block.get("row", math.inf), row_id, item))
    return {
        seed: [(row_id, item) for _, row_id, item in sorted(items, key=lambda entry: entry[:2])]
        for seed, items in by_seed.items()
    }


def seed_two_stage(result: TwoStageResult, stages: TwoStageSplit) -> dict[str, Any]:
    """Return what a seed's Result keeps of its two-stage result beyond its combined row: the stage summaries,
    each group's parts, value, detail and the weights of its synthetic tokens (per stage-one frame), and the
    notes."""
    entries = {entry.original: entry for entry in stages.groups or ()}
    return json_safe(
        {
            "stage_one": result.stage_one,
            "stage_two": result.stage_two,
            "groups": [
                {
                    "original": group.original,
                    "previous": group.previous,
                    "parts": group.parts,
                    "combined": group.combined,
                    "detail": group.detail,
                    "weights": {
                        role: {token: result.weights.get(token, math.nan) for token in tokens}
                        for role, tokens in (
                            ("original", entries[group.original].now_tokens),
                            ("previous", entries[group.original].previous_tokens),
                        )
                    },
                }
                for group in result.groups
            ],
            "official": result.official,
            "notes": list(result.notes[:MAX_KEPT_NOTES]),
            "note_count": len(result.notes),
        }
    )


def _weighted_detail(detail: dict[str, Any], result: TwoStageResult, token: str) -> dict[str, Any]:
    """Return a row's detail with its weight (stage-one rows of a group weigh 1) and how it came about."""
    block = dict(detail.get(DETAIL_KEY, {}))
    if token in result.weights:
        block["weight"] = result.weights[token]
    if token in result.weight_detail:
        block["weighting"] = json_safe(result.weight_detail[token])
    return {**detail, DETAIL_KEY: block}


def aggregate_two_stage_run(
    session: Session, submission: Submission, version: str, engine_version: str, bootstrap_samples: int
) -> None:
    """Write the Results (one per seed) and the Summary of a complete two-stage run under `version`, and each
    row's weight (the caller has deleted the earlier Results and Summaries)."""
    from scorer.two_stage.aggregate import aggregate_two_stage

    stages = stage_mapping(submission.split)
    columns = get_version(version).result_columns
    worker_rows = select(TokenResultRow.seed, TokenResultRow.worker, TokenResultRow.duration_s).where(
        TokenResultRow.submission_id == submission.id,
        TokenResultRow.run == submission.run,
        TokenResultRow.metric_version == version,
    )
    workers: dict[int, set[str]] = defaultdict(set)
    durations: dict[int, list[float]] = defaultdict(list)
    for seed, worker, duration in session.execute(worker_rows).all():
        workers[seed].add(worker)
        durations[seed].append(duration)
    per_seed: list[TwoStageResult] = []
    failed_anywhere: set[str] = set()
    for seed, items in sorted(_seed_tokens(session, submission, version).items()):
        result = aggregate_two_stage([item for _, item in items], stages)
        per_seed.append(result)
        failed = {row.token for row in result.rows if not row.valid}
        failed_anywhere |= failed
        session.execute(
            update(TokenResultRow),
            [
                {"id": row_id, "detail": _weighted_detail(item.result.detail, result, item.result.token)}
                for row_id, item in items
            ],
        )
        session.add(
            seed_result(
                submission,
                version,
                ALL_SUBSET,
                seed,
                tokens=len(result.rows),
                failed=len(failed),
                engine_version=engine_version,
                workers=workers[seed],
                duration_s=float(sum(durations[seed])),
                means={column: result.combined.get(column) for column in columns},
                two_stage=seed_two_stage(result, stages),
            )
        )
    session.add(_summary(submission, version, columns, per_seed, len(failed_anywhere), bootstrap_samples))


def _summary(
    submission: Submission,
    version: str,
    columns: tuple[str, ...],
    per_seed: list[TwoStageResult],
    failed: int,
    bootstrap_samples: int,
) -> Summary:
    """Combine the seeds of a two-stage entry: each column's mean over seeds (undefined seeds left out), the
    spread of the combined score, and its interval over groups."""
    group_values = np.array([[group.combined["score"] for group in result.groups] for result in per_seed])
    averaged = group_values.mean(axis=0) if group_values.size else np.zeros(0)
    defined = averaged[~np.isnan(averaged)]
    [interval] = bootstrap_cis(defined[None, :], bootstrap_samples)
    stage_means = {
        stage: {
            column: stored_value(defined_mean([getattr(result, stage)[column] for result in per_seed]))
            for column in columns
        }
        for stage in ("stage_one", "stage_two")
    }
    return seed_summary(
        submission.id,
        version,
        ALL_SUBSET,
        np.array([result.score for result in per_seed]),
        interval,
        tokens=submission.token_count,
        failed=failed,
        means={column: defined_mean([result.combined[column] for result in per_seed]) for column in columns},
        two_stage=json_safe(
            {
                **stage_means,
                "groups": len(averaged),
                "undefined_groups": int(np.count_nonzero(np.isnan(averaged))),
                "official": all(result.official for result in per_seed),
            }
        ),
    )
