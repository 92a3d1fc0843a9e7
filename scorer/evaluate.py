"""Score submitted trajectories against a split: caches in, per-token results out.

Unlike the devkit, one bad token never aborts the others: it becomes an invalid row with an error
text. Summaries count such a token as 0 (the devkit's average row skips it) and report how many
(docs/engine.md, "Split results").
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scorer.cache import MetricCache, build_cache_batch, load_cache, save_cache
from scorer.geometry import FloatArray
from scorer.pdm_scorer import ProposalScores, join_measures, measure_batch, score_measures
from scorer.scene import Scene, SceneFormatError, load_scene, scene_file_hash, scene_paths
from scorer.simulation import simulate
from scorer.trajectory import agent_references, initial_state
from scorer.versions import METRIC_COLUMNS, VERSIONS, MetricVersion, get_version

POSES_SHAPE = (8, 3)
CHUNK_SIZE = 256  # tokens per batched simulation; bounds memory on large splits
CACHE_BATCH_SIZE = 16  # scenes whose caches are built together (a wider batch gains little)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TokenResult:
    """One row of the result table: the devkit's columns for one token (and seed)."""

    token: str
    seed: int | None
    valid: bool
    metrics: dict[str, float] = field(default_factory=dict)
    error: str | None = None


class TokenError(Exception):
    """A token that cannot be scored; the message is safe to show to the submitting team."""


def split_content_hash(split_dir: Path) -> str:
    """Return a hash over (token, scene file hash) of the split in token order."""
    digest = hashlib.sha256()
    for token, path in scene_paths(split_dir).items():
        digest.update(f"{token}:{scene_file_hash(path)}\n".encode())
    return digest.hexdigest()


def _build_and_save(
    scenes: Sequence[Scene], cache_dir: Path, versions: Sequence[str]
) -> list[dict[str, MetricCache]]:
    caches = build_cache_batch(scenes, [get_version(name) for name in versions])
    for scene_caches in caches:
        for cache in scene_caches.values():
            save_cache(cache, cache_dir)
    return caches


def build_missing_caches(
    paths: Sequence[Path], cache_dir: Path, versions: Sequence[str]
) -> tuple[dict[str, dict[str, MetricCache]], dict[str, Exception]]:
    """Build and save whatever the cache lacks of `versions` for the scenes at `paths`, in batches.

    Return the caches built, by scene file name, and the error of each scene that failed, by file name:
    a batch that fails is built again scene by scene, so an error names its scene and the others go on.
    """
    built: dict[str, dict[str, MetricCache]] = {}
    errors: dict[str, Exception] = {}
    lacking: dict[tuple[str, ...], list[tuple[str, Scene]]] = {}  # scenes grouped by what they lack
    for path in paths:
        try:
            token, scene_hash = path.name.split(".")[0], scene_file_hash(path)
            missing = tuple(v for v in versions if load_cache(cache_dir, v, token, scene_hash) is None)
            if missing:
                lacking.setdefault(missing, []).append((path.name, load_scene(path)))
        except (SceneFormatError, OSError) as error:  # unreadable or invalid: this scene only
            errors[path.name] = error
    for missing, named in lacking.items():
        for start in range(0, len(named), CACHE_BATCH_SIZE):
            batch = named[start : start + CACHE_BATCH_SIZE]
            try:
                results = list(
                    zip(
                        batch, _build_and_save([scene for _, scene in batch], cache_dir, missing), strict=True
                    )
                )
            except Exception:  # noqa: BLE001 - a scene broke the batch: build each alone to find it
                results = []
                for item in batch:
                    try:
                        results.append((item, _build_and_save([item[1]], cache_dir, missing)[0]))
                    except Exception as error:
                        log.exception("metric cache of %s could not be built", item[0])
                        errors[item[0]] = error
            built |= {name: caches for (name, _), caches in results}
    return built, errors


def _build_split_part(task: tuple[tuple[Path, ...], Path, tuple[str, ...]]) -> tuple[int, dict[str, str]]:
    paths, cache_dir, versions = task
    _, errors = build_missing_caches(paths, cache_dir, versions)
    return len(paths), {name: f"{type(error).__name__}: {error}" for name, error in errors.items()}


def build_split_cache(
    split_dir: Path,
    cache_dir: Path,
    versions: Sequence[str],
    workers: int = 1,
    progress: Callable[[int], None] | None = None,
) -> dict[str, str]:
    """Build every missing or stale cache of a split; return file name -> error of scenes that failed."""
    paths = list(scene_paths(split_dir).values())
    tasks = [
        (tuple(paths[start : start + CACHE_BATCH_SIZE]), Path(cache_dir), tuple(versions))
        for start in range(0, len(paths), CACHE_BATCH_SIZE)
    ]
    failures: dict[str, str] = {}
    results: Iterator[tuple[int, dict[str, str]]]
    if workers > 1:
        executor = ProcessPoolExecutor(max_workers=workers)
        results = executor.map(_build_split_part, tasks)
    else:
        executor = None
        results = map(_build_split_part, tasks)
    try:
        for count, errors in results:
            failures |= errors
            if progress is not None:
                progress(count)
    finally:
        if executor is not None:
            executor.shutdown()
    return failures


def _build_error_text(token: str, error: Exception) -> str:
    """Return what a team may read of why a hidden scene's cache is missing: never the scene's content nor
    the server's paths, which the error's own text quotes (it goes to the log, for the organisers)."""
    log.warning("token %s: metric cache not built: %s: %s", token, type(error).__name__, error)
    if isinstance(error, (SceneFormatError, OSError)):
        return "the hidden scene of this token is unreadable on the server (the organisers are told)"
    return f"the metric cache of this hidden scene could not be built ({type(error).__name__})"


def _checked_poses(poses: object) -> FloatArray:
    array = np.asarray(poses, dtype=np.float64)
    if array.shape != POSES_SHAPE:
        raise TokenError(f"poses: expected shape {POSES_SHAPE}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise TokenError("poses: non-finite value")
    return array


def _row(token: str, seed: int | None, scores: object, index: tuple[int, int]) -> TokenResult:
    metrics = {column: float(getattr(scores, column)[index]) for column in METRIC_COLUMNS}
    return TokenResult(token=token, seed=seed, valid=True, metrics=metrics)


def score_against_references(
    caches: Sequence[MetricCache], poses: Sequence[FloatArray], version: MetricVersion
) -> tuple[FloatArray, ProposalScores]:
    """Return the agents' simulated states (B, 41, 11) and the scores (B, 2) of [PDM-Closed, agent] per token,
    as the devkit scores them: proposal 0 is the cached PDM-Closed reference (it sets the progress
    normaliser), proposal 1 the agent. Raises ValueError when a simulation diverges."""
    initial = np.stack([initial_state(cache.ego) for cache in caches])
    t0_us = np.array([cache.t0_us for cache in caches], dtype=np.int64)
    states = simulate(agent_references(initial, t0_us, np.stack(poses)), initial)
    agent = measure_batch(
        states[:, None],
        [cache.observation for cache in caches],
        [cache.drivable_map for cache in caches],
        [cache.centerline[:, :2] for cache in caches],
        [cache.route_lane_ids for cache in caches],
        version.evaluation,
    )
    reference = join_measures([cache.reference_measures for cache in caches], axis=0)
    return states, score_measures(join_measures([reference, agent]), version.evaluation)


def score_caches(
    caches: Sequence[MetricCache],
    poses: Sequence[FloatArray],
    version: MetricVersion,
    seed: int | None = None,
) -> list[TokenResult]:
    """Score one agent trajectory per cache, all tokens in one batch, against the cached PDM-Closed measures."""
    if not caches:
        return []
    try:
        _, scores = score_against_references(caches, poses, version)
    except ValueError:
        if len(caches) == 1:
            raise
        # One diverging trajectory must not fail its neighbours: score them one by one.
        return [
            result for c, p in zip(caches, poses, strict=True) for result in _score_one(c, p, version, seed)
        ]
    return [_row(cache.token, seed, scores, (index, 1)) for index, cache in enumerate(caches)]


def _score_one(
    cache: MetricCache, poses: FloatArray, version: MetricVersion, seed: int | None
) -> list[TokenResult]:
    try:
        return score_caches([cache], [poses], version, seed)
    except ValueError as error:
        return [TokenResult(cache.token, seed, False, error=f"scoring failed: {error}")]


def score_tokens(
    split_dir: Path,
    cache_dir: Path,
    predictions: Mapping[str, object],
    version: str,
    tokens: Sequence[str] | None = None,
    seed: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> list[TokenResult]:
    """Return one result per token (all tokens of the split by default), building whatever the cache lacks."""
    metric_version = get_version(version)
    paths = scene_paths(split_dir)
    tokens = list(paths) if tokens is None else list(tokens)
    results: list[TokenResult] = []
    for start in range(0, len(tokens), CHUNK_SIZE):
        chunk = tokens[start : start + CHUNK_SIZE]
        ready: list[tuple[MetricCache, FloatArray]] = []
        unbuilt: list[tuple[str, FloatArray]] = []
        for token in chunk:
            try:
                if token not in paths:
                    raise TokenError("token is not part of the split")
                if token not in predictions:
                    raise TokenError("no prediction for this token")
                poses = _checked_poses(predictions[token])
            except TokenError as error:
                results.append(TokenResult(token, seed, False, error=str(error)))
                continue
            cache = load_cache(Path(cache_dir), version, token, scene_file_hash(paths[token]))
            if cache is None:
                unbuilt.append((token, poses))
            else:
                ready.append((cache, poses))
        # Every version at once: one PDM-Closed unroll serves them all, and the others are scored next.
        built, errors = build_missing_caches(
            [paths[token] for token, _ in unbuilt], Path(cache_dir), list(VERSIONS)
        )
        for token, poses in unbuilt:
            name = paths[token].name
            if name in built:
                ready.append((built[name][version], poses))
            else:
                results.append(TokenResult(token, seed, False, error=_build_error_text(token, errors[name])))
        results.extend(score_caches([c for c, _ in ready], [p for _, p in ready], metric_version, seed))
        if progress is not None:
            progress(len(chunk))
    order = {token: index for index, token in enumerate(tokens)}
    return sorted(results, key=lambda result: order[result.token])


def summarize(results: Sequence[TokenResult]) -> dict[str, float]:
    """Return the mean of every column over tokens, an unscored token counting 0, and the failed count."""
    summary = {
        column: float(np.mean([r.metrics.get(column, 0.0) for r in results])) if results else float("nan")
        for column in METRIC_COLUMNS
    }
    summary["tokens"] = float(len(results))
    summary["failed"] = float(sum(not r.valid for r in results))
    return summary
