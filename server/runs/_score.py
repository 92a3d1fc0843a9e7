"""Scoring a chunk's tokens with the engine: every seed and version at once (a token's caches read once, each
trajectory simulated once), or, for a token that killed its workers, failed rows naming the cause."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from time import perf_counter
from typing import TYPE_CHECKING, Any

from server.models import SplitKind
from server.object_store import ObjectStore
from server.runs._job import ChunkInputs, ScoringJob, trajectories
from server.runs._two_stage import stage_rows

if TYPE_CHECKING:
    from scorer.evaluate import TokenResult

POISONED_TOKEN = (
    "scoring this token stopped the worker process twice (a crash or running out of memory); "
    "it was not scored and counts as a failed token"
)


@dataclass(frozen=True)
class ScoredChunk:
    """A chunk's rows per metric version, and the scoring time each version's rows share."""

    rows: Mapping[str, Sequence[TokenResult]]
    seconds_per_version: float
    admin_note: str | None = None  # what admins read of the run's problems (the team sees per-token errors)


def score_chunk(inputs: ChunkInputs, store: ObjectStore, cache_dir: Path) -> ScoredChunk:
    """Score the chunk's tokens without rows (raises Rejected when the run's file cannot be used)."""
    # The engine is heavy: the API imports this package without it.
    from scorer.evaluate import TokenResult, score_seeds

    job = inputs.job
    if inputs.poisoned:
        failed = [
            TokenResult(token, seed, valid=False, error=POISONED_TOKEN)
            for seed in range(job.seed_count)
            for token in inputs.todo
        ]
        note = f"token {', '.join(inputs.todo)}: written as failed, {POISONED_TOKEN}"
        if job.split_kind == SplitKind.two_stage:
            failed = _stage_failed(failed, trajectories(job, store))
        return ScoredChunk(dict.fromkeys(job.versions, failed), 0.0, admin_note=note)
    if not inputs.todo:  # every row was written by an earlier holder: only the run's completion is left
        return ScoredChunk({}, 0.0)
    seeds: dict[int | None, Mapping[str, object]] = dict(enumerate(trajectories(job, store)))
    started = perf_counter()
    if job.split_kind == SplitKind.two_stage:
        rows = {version: _two_stage_rows(job, cache_dir, seeds, version, inputs) for version in job.versions}
    else:
        rows = score_seeds(job.split_dir, cache_dir, seeds, job.versions, inputs.todo, context=inputs.context)
    return ScoredChunk(rows, (perf_counter() - started) / len(job.versions))


def _two_stage_rows(
    job: ScoringJob, cache_dir: Path, seeds: Mapping[int | None, Any], version: str, inputs: ChunkInputs
) -> list[TokenResult]:
    """Score a two-stage chunk's tokens beside their comfort partners (its context) under `version`."""
    from scorer.two_stage.score import score_two_stage_part

    scored = score_two_stage_part(job.split_dir, cache_dir, seeds, version, inputs.todo, inputs.context)
    return stage_rows(scored, {seed: list(predictions) for seed, predictions in seeds.items()})


def _stage_failed(failed: Sequence[TokenResult], seeds: Sequence[Mapping[str, object]]) -> list[TokenResult]:
    """Return a two-stage chunk's failed rows with their place in the submission (what the aggregation orders
    rows by); their start point and endpoint are unknown: their successors are weighted alike."""
    from scorer.two_stage.aggregate import TwoStageToken

    unknown = (math.nan, math.nan)
    by_seed: dict[int | None, list[TwoStageToken]] = {}
    for row in failed:
        by_seed.setdefault(row.seed, []).append(TwoStageToken(row, unknown, unknown))
    return stage_rows(by_seed, {seed: list(seeds[seed or 0]) for seed in by_seed})
