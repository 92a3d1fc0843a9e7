"""Scoring a chunk's tokens with the engine: every seed and version at once (a token's caches read once, each
trajectory simulated once), or, for a token that killed the process scoring it alone, failed rows naming the
cause."""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from time import perf_counter
from typing import TYPE_CHECKING, Any

from server.models import FailureKind, SplitKind
from server.object_store import ObjectStore
from server.runs._job import ChunkInputs, Rejected, ScoringJob, trajectories
from server.runs._two_stage import stage_rows
from server.split_store import (
    SplitStoreError,
    is_stored_split,
    local_scenes,
    mirror_dir,
    split_stages,
    stored_scene_files,
)

if TYPE_CHECKING:
    from scorer.evaluate import SceneFiles, TokenResult
    from scorer.two_stage.split import TwoStageSplit

SPLIT_UNREADABLE = "the split's scenes cannot be read from the server's store; the organisers are told"
POISONED_TOKEN = (
    "scoring this token stopped its process (a crash or running out of memory); "
    "it was not scored and counts as a failed token"
)


@dataclass(frozen=True)
class ScoredChunk:
    """A chunk's rows per metric version, and the scoring time each version's rows share."""

    rows: Mapping[str, Sequence[TokenResult]]
    seconds_per_version: float
    admin_note: str | None = None  # what admins read of the run's problems (the team sees per-token errors)


def score_chunk(
    inputs: ChunkInputs, store: ObjectStore, cache_dir: Path, cache_store: ObjectStore | None = None
) -> ScoredChunk:
    """Score the chunk's tokens without rows (raises Rejected when the run's file or the split's scenes cannot
    be used; StoreUnavailable while the object store does not answer). With `cache_store`, the metric caches
    of the chunk's scenes come from there when another worker built them, and go there when built here."""
    # The engine is heavy: the API imports this package without it.
    from scorer.evaluate import SceneFiles, TokenResult, score_seeds
    from scorer.scene import scene_paths
    from server.shared_caches import fetch_caches, keep_caches, publish_caches, publish_packs

    job = inputs.job
    if inputs.process_death is not None:
        failed = [
            TokenResult(token, seed, valid=False, error=POISONED_TOKEN)
            for seed in range(job.seed_count)
            for token in inputs.todo
        ]
        note = f"token {', '.join(inputs.todo)}: written as failed, its process {inputs.process_death}"
        if job.split_kind == SplitKind.two_stage:
            with _split_read():
                failed = _stage_failed(failed, trajectories(job, store))
        return ScoredChunk(dict.fromkeys(job.versions, failed), 0.0, admin_note=note)
    if not inputs.todo:  # every row was written by an earlier holder: only the run's completion is left
        return ScoredChunk({}, 0.0)
    scored = {*inputs.todo, *inputs.context}
    with _split_read():
        seeds: dict[int | None, Mapping[str, object]] = dict(enumerate(trajectories(job, store)))
        stages = None
        if job.split_kind == SplitKind.two_stage:  # a part reads its scenes (their starts): fetched first
            split_dir = local_scenes(job.split_source, job.split_hash, scored)
            stages = split_stages(job.split_source, job.split_hash)
            scenes = SceneFiles(scene_paths(split_dir))
        else:
            split_dir, scenes = _one_stage_scenes(job)
    if cache_store is not None:
        hashes = {token: scenes.file_hash(token) for token in scored if token in scenes.paths}
        fetched = fetch_caches(cache_store, cache_dir, hashes, inputs.packs)
        if stages is None:
            scenes = scenes._replace(caches=fetched.caches)
        else:  # a two-stage part reads every cache from cache_dir
            keep_caches(cache_dir, fetched.caches)
    started = perf_counter()
    with _split_read():  # the scenes of the caches to build are fetched as the engine needs them
        if stages is not None:
            rows = {
                version: _two_stage_rows(split_dir, stages, cache_dir, seeds, version, inputs)
                for version in job.versions
            }
        else:
            rows = score_seeds(
                split_dir, cache_dir, seeds, job.versions, inputs.todo, context=inputs.context, scenes=scenes
            )
    if cache_store is not None:
        publish_caches(cache_store, cache_dir, {token: hashes[token] for token in fetched.unbuilt})
        publish_packs(cache_store, cache_dir, hashes, fetched.unpacked)
    return ScoredChunk(rows, (perf_counter() - started) / len(job.versions))


def _one_stage_scenes(job: ScoringJob) -> tuple[Path, SceneFiles]:
    """Return the directory and the scene files of a one-stage run's split: a local split's, listed once for
    the chunk; a stored split's mirror, its files from the manifest, each fetched only when its metric cache
    is to be built (`SceneFiles`)."""
    from scorer.evaluate import SceneFiles
    from scorer.scene import scene_paths

    if not is_stored_split(job.split_source):
        return Path(job.split_source), SceneFiles(scene_paths(job.split_source))
    paths, hashes = stored_scene_files(job.split_source, job.split_hash)
    fetch = partial(local_scenes, job.split_source, job.split_hash)
    return mirror_dir(job.split_hash), SceneFiles(paths, hashes, fetch)


@contextmanager
def _split_read() -> Iterator[None]:
    """Turn a stored split that cannot be read (its manifest, stage mapping or a scene) into the run's
    Rejected, naming the object for the organisers."""
    try:
        yield
    except SplitStoreError as error:
        raise Rejected(FailureKind.infrastructure, SPLIT_UNREADABLE, str(error)) from None


def _two_stage_rows(
    split_dir: Path,
    stages: TwoStageSplit,
    cache_dir: Path,
    seeds: Mapping[int | None, Any],
    version: str,
    inputs: ChunkInputs,
) -> list[TokenResult]:
    """Score a two-stage chunk's tokens beside their comfort partners (its context) under `version`."""
    from scorer.two_stage.score import score_two_stage_part

    scored = score_two_stage_part(split_dir, stages, cache_dir, seeds, version, inputs.todo, inputs.context)
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
