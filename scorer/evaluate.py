"""Score submitted trajectories against a split: caches in, per-token results out.

Unlike the devkit, one bad token never aborts the others: it becomes an invalid row with an error
text. Summaries count such a token as 0 (the devkit's average row skips it) and report how many
(docs/engine.md, "Split results").
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import math
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from scorer.cache import MetricCache, build_cache_batch, load_cache, save_cache
from scorer.geometry import FloatArray
from scorer.human import filtered, is_synthetic
from scorer.metrics.aggregation import aggregate
from scorer.metrics.two_frame_comfort import FEATURES, overlap_steps, two_frame_extended_comfort
from scorer.pdm_scorer import (
    RESULT_COLUMN_OF_ROW,
    ProposalScores,
    join_measures,
    measure_batch,
    score_measures,
)
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
    metrics: dict[str, float] = field(default_factory=dict)  # NaN where a column is undefined (v2.2's EC)
    error: str | None = None
    detail: dict[str, Any] = field(default_factory=dict)  # what a team may read of how the row came about


@dataclass(frozen=True, eq=False)
class ScoredToken:
    """A valid row before the split-level step (v2.2's EC), with what that step reads."""

    result: TokenResult
    log_name: str
    t0_us: int
    states: FloatArray  # (41, 11) the agent's simulated states


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
                results = [(item, _build_alone(item, cache_dir, missing, errors)) for item in batch]
            built |= {name: caches for (name, _), caches in results if caches}
    return built, errors


def _build_alone(
    item: tuple[str, Scene], cache_dir: Path, versions: Sequence[str], errors: dict[str, Exception]
) -> dict[str, MetricCache]:
    """Build one scene's caches, a version at a time if need be, so that a scene one version cannot take
    (v2.2 needs 3 past frames) is still scored under the others; record the scene's error."""
    name, scene = item
    try:
        return _build_and_save([scene], cache_dir, versions)[0]
    except Exception:  # noqa: BLE001 - find which versions fail
        caches: dict[str, MetricCache] = {}
        for version in versions:
            try:
                caches |= _build_and_save([scene], cache_dir, [version])[0]
            except Exception as error:
                log.exception("metric cache of %s under %s could not be built", name, version)
                errors[name] = error
        return caches


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


def token_result(
    cache: MetricCache, seed: int | None, scores: ProposalScores, index: int, version: MetricVersion
) -> TokenResult:
    """Return the agent's row of token `index` in `scores`, the token scored alone (v2.2: filtered, EC undefined)."""
    agent = {
        column: float(getattr(scores, column)[index, 1])
        for column in version.result_columns
        if column in ROW_COLUMNS
    }
    if version.two_frame_extended_comfort_weight is None:
        return TokenResult(token=cache.token, seed=seed, valid=True, metrics=agent)
    detail: dict[str, Any] = {}
    if version.human_penalty_filter and cache.human is not None:
        metrics, overridden = filtered(agent, cache.human)
        detail["human_filter"] = {"overridden": overridden, "agent_before": agent, "human": cache.human}
    else:
        metrics = agent
        reason = (
            "synthetic scene (17-character token)" if is_synthetic(cache.token) else "off in this version"
        )
        detail["human_filter"] = {"overridden": [], "not_applied": reason}
    metrics["two_frame_extended_comfort"] = float("nan")
    metrics["score"] = extended_score(metrics, version)
    return TokenResult(token=cache.token, seed=seed, valid=True, metrics=metrics, detail=detail)


# Result columns that come straight from the scorer's rows (v2.2 adds EC and recomputes the score per split).
ROW_COLUMNS = tuple(
    dict.fromkeys(
        column
        for version in VERSIONS.values()
        for column in version.result_columns
        if column != "two_frame_extended_comfort"
    )
)


def extended_score(metrics: Mapping[str, float], version: MetricVersion) -> float:
    """Return v2's final score of one row (`compute_final_scores`): the multipliers' product times the weighted
    mean of EP, TTC, LK, HC and EC, where an undefined EC (NaN) drops out with its weight (/16 or /14)."""
    config = version.evaluation
    two_frame = metrics["two_frame_extended_comfort"]
    defined = not math.isnan(two_frame)
    multipliers = np.array([[metrics[RESULT_COLUMN_OF_ROW[row]]] for row in config.multiplier_rows])
    weighted = [metrics[RESULT_COLUMN_OF_ROW[row]] for row in config.weights] + [
        two_frame if defined else 0.0
    ]
    weights = [*config.weights.values(), version.two_frame_extended_comfort_weight if defined else 0.0]
    return float(aggregate(multipliers, np.array(weighted)[:, None], np.array(weights))[0])


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
    pasts = [cache.past_states for cache in caches]
    return states, score_measures(join_measures([reference, agent]), version.evaluation, pasts)


def score_caches(
    caches: Sequence[MetricCache],
    poses: Sequence[FloatArray],
    version: MetricVersion,
    seed: int | None = None,
) -> list[TokenResult]:
    """Score one agent trajectory per cache, all tokens in one batch, against the cached PDM-Closed measures.

    Each token is scored alone: v2.2's EC, which pairs tokens, is left undefined (`join_two_frame_comfort`).
    """
    return [
        item.result if isinstance(item, ScoredToken) else item
        for item in _scored(caches, poses, version, seed)
    ]


def _scored(
    caches: Sequence[MetricCache], poses: Sequence[FloatArray], version: MetricVersion, seed: int | None
) -> list[ScoredToken | TokenResult]:
    if not caches:
        return []
    try:
        states, scores = score_against_references(caches, poses, version)
    except ValueError:
        if len(caches) == 1:
            raise
        # One diverging trajectory must not fail its neighbours: score them one by one.
        return [item for c, p in zip(caches, poses, strict=True) for item in _score_one(c, p, version, seed)]
    return [
        ScoredToken(
            token_result(cache, seed, scores, index, version), cache.log_name, cache.t0_us, states[index]
        )
        for index, cache in enumerate(caches)
    ]


def _score_one(
    cache: MetricCache, poses: FloatArray, version: MetricVersion, seed: int | None
) -> list[ScoredToken | TokenResult]:
    try:
        return _scored([cache], [poses], version, seed)
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
    context: Sequence[str] = (),
) -> list[TokenResult]:
    """Return one result per token (all tokens of the split by default), building whatever the cache lacks.

    `context` tokens are scored too, under a version with two-frame comfort, for their rows to pair with
    `tokens` (`pairing_contexts`), and are not returned.
    """
    metric_version = get_version(version)
    paths = scene_paths(split_dir)
    tokens = list(paths) if tokens is None else list(tokens)
    if metric_version.two_frame_extended_comfort_weight is None:
        context = ()
    requested = set(tokens)
    scored_tokens = tokens + [token for token in dict.fromkeys(context) if token not in requested]
    results: list[TokenResult | ScoredToken] = []
    for start in range(0, len(scored_tokens), CHUNK_SIZE):
        chunk = scored_tokens[start : start + CHUNK_SIZE]
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
            if version in built.get(name, {}):
                ready.append((built[name][version], poses))
            else:
                results.append(TokenResult(token, seed, False, error=_build_error_text(token, errors[name])))
        results.extend(_scored([c for c, _ in ready], [p for _, p in ready], metric_version, seed))
        if progress is not None:
            progress(len(chunk))
    scored = [item for item in results if isinstance(item, ScoredToken)]
    rows = [item for item in results if isinstance(item, TokenResult)]
    rows += join_two_frame_comfort(scored, metric_version) if scored else []
    order = {token: index for index, token in enumerate(tokens)}
    return sorted((row for row in rows if row.token in order), key=lambda result: order[result.token])


def summarize(results: Sequence[TokenResult], columns: Sequence[str] = METRIC_COLUMNS) -> dict[str, float]:
    """Return the mean of every column over tokens, an unscored token counting 0, and the failed count.

    An undefined value (v2.2's EC without an adjacent frame) is left out of its column's mean, as the
    devkit's average row skips NaN; a column undefined everywhere is NaN.
    """

    def mean(values: list[float]) -> float:
        defined = [value for value in values if not math.isnan(value)]
        return float(np.mean(defined)) if defined else float("nan")

    summary = {column: mean([r.metrics.get(column, 0.0) for r in results]) for column in columns}
    summary["tokens"] = float(len(results))
    summary["failed"] = float(sum(not r.valid for r in results))
    return summary


ADJACENT_GAP_S = 0.55  # `infer_start_adjacent_mapping`'s time_gap_threshold


def adjacent_pairs(scored: Sequence[ScoredToken]) -> dict[int, int]:
    """Return, for each row that pairs with the row before it in its log, that row:
    `infer_start_adjacent_mapping` over valid original rows, grouped by log and sorted by start time (seconds
    as the devkit's float `timestamp_us * 1e-6`; ties by token, where pandas' sort is not stable)."""
    start_s = [item.t0_us * 1e-6 for item in scored]
    by_log: dict[str, list[int]] = {}
    for index, item in enumerate(scored):
        if not is_synthetic(item.result.token):
            by_log.setdefault(item.log_name, []).append(index)
    for members in by_log.values():
        members.sort(key=lambda index: (start_s[index], scored[index].result.token))
    return {
        current: previous
        for members in by_log.values()
        for previous, current in itertools.pairwise(members)
        if abs(start_s[current] - start_s[previous]) <= ADJACENT_GAP_S
    }


def pairing_contexts(
    starts: Mapping[str, tuple[str, int]], groups: Sequence[Collection[str]]
) -> list[list[str]]:
    """Return, for each group of tokens scored on its own, the tokens outside it that two-frame comfort may pair
    its tokens with: the frames of the same log that start at most ADJACENT_GAP_S before a token (ties too).

    Scored beside a group (`score_tokens`' `context`), they give each token the EC it gets when the whole split
    is scored at once: `adjacent_pairs` pairs a token with the latest valid frame before it in its log, and with
    none when that frame is further away. `starts` is token -> (log name, t0 in us), `scene_start`'s answer.
    """
    by_log: dict[str, list[str]] = {}
    for token, (log_name, _) in starts.items():
        if not is_synthetic(token):
            by_log.setdefault(log_name, []).append(token)
    start_s = {token: t0_us * 1e-6 for token, (_, t0_us) in starts.items()}
    position: dict[str, tuple[list[str], int]] = {}
    for members in by_log.values():
        members.sort(key=lambda token: (start_s[token], token))
        position.update((token, (members, index)) for index, token in enumerate(members))
    contexts = []
    for group in groups:
        context: dict[str, None] = {}
        for token in group:
            members, index = position.get(token, ([], 0))
            earlier = index - 1
            while earlier >= 0 and abs(start_s[token] - start_s[members[earlier]]) <= ADJACENT_GAP_S:
                if members[earlier] not in group:
                    context[members[earlier]] = None
                earlier -= 1
        contexts.append(list(context))
    return contexts


def join_two_frame_comfort(scored: Sequence[ScoredToken], version: MetricVersion) -> list[TokenResult]:
    """Return the rows with v2.2's two-frame extended comfort (EC) and the final score: EC between each row and
    the adjacent earlier frame of its log scored in the same run and seed, NaN (weight dropped) elsewhere.

    Where the devkit pairs two frames and then fails on them (start times equal, 0.55 s apart to the float, or
    under 0.05 s apart), EC is undefined and the row's detail says why.
    """
    if version.two_frame_extended_comfort_weight is None:
        return [item.result for item in scored]
    pairs = adjacent_pairs(scored)
    details: dict[int, dict[str, Any]] = {
        index: {"previous_token": scored[previous].result.token} for index, previous in pairs.items()
    }
    computed: list[tuple[int, int, int]] = []  # (row, previous row, steps)
    for index, previous in pairs.items():
        try:
            computed.append((index, previous, overlap_steps(scored[index].t0_us, scored[previous].t0_us)))
        except ValueError as error:
            details[index]["undefined"] = f"the official code pairs this frame and then fails: {error}"
    values: dict[int, tuple[float, dict[str, float]]] = {}
    if computed:
        rows, previous_rows, steps = (list(column) for column in zip(*computed, strict=True))
        comfort = two_frame_extended_comfort(
            np.stack([scored[row].states for row in rows]),
            np.stack([scored[row].states for row in previous_rows]),
            steps,
        )
        for position, row in enumerate(rows):
            values[row] = (
                float(comfort.value[position]),
                dict(zip(FEATURES, comfort.rms[position].tolist(), strict=True)),
            )
    results = []
    for index, item in enumerate(scored):
        if index not in details:
            results.append(item.result)
            continue
        metrics, detail = dict(item.result.metrics), dict(item.result.detail)
        if index in values:
            metrics["two_frame_extended_comfort"], rms = values[index]
            details[index]["rms"] = rms
            metrics["score"] = extended_score(metrics, version)
        detail["two_frame_extended_comfort"] = details[index]
        results.append(replace(item.result, metrics=metrics, detail=detail))
    return results
