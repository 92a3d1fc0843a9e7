"""Score submitted trajectories against a split: caches in, per-token results out.

Unlike the devkit, one bad token never aborts the others: it becomes an invalid row with an error
text. Summaries count such a token as 0 (the devkit's average row skips it) and report how many
(docs/engine.md, "Split results").
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
import hashlib
import itertools
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, NamedTuple, TypeVar

import numpy as np

from scorer.cache import (
    MetricCache,
    ObservationKey,
    build_cache_batch,
    load_caches,
    observation_key,
    save_caches,
)
from scorer.collector import collector_paused
from scorer.geometry import BoolArray, FloatArray
from scorer.human import filtered, is_synthetic
from scorer.metrics.aggregation import aggregate, defined_mean
from scorer.metrics.two_frame_comfort import (
    ADJACENT_GAP_S,
    FEATURES,
    overlap_steps,
    two_frame_extended_comfort,
)
from scorer.observation import Observation
from scorer.pdm_scorer import (
    RESULT_COLUMN_OF_ROW,
    MeasureSettings,
    ProposalMeasures,
    ProposalScores,
    comfort_of,
    join_measures,
    measure_alike,
    score_measures,
)
from scorer.scene import Scene, SceneFormatError, load_scene, scene_file_hash, scene_paths
from scorer.simulation import simulate
from scorer.trajectory import agent_references, initial_state
from scorer.versions import (
    METRIC_COLUMNS,
    VERSIONS,
    MetricVersion,
    cache_source,
    cached_together,
    get_version,
)

if TYPE_CHECKING:
    import logging

POSES_SHAPE = (8, 3)
CHUNK_SIZE = 256  # tokens per batched simulation; bounds memory on large splits
# Scenes whose caches are built together at most. Without AVX-512 the SVML replays (arctan2, tan, pow) cost
# most per call, 120 calls a simulation: 64 scenes take about a quarter less CPU time a scene than 16.
CACHE_BATCH_SIZE = 64
Key = TypeVar("Key", str, tuple[int | None, str])


@dataclass(frozen=True)
class TokenResult:
    """One row of the result table: the devkit's columns for one token (and seed)."""

    token: str
    seed: int | None
    valid: bool
    metrics: dict[str, float] = field(default_factory=dict)  # NaN where a column is undefined (v2.2's EC)
    error: str | None = None
    detail: dict[str, Any] = field(default_factory=dict)  # what a team may read of how the row came about


class ScoredToken(NamedTuple):
    """A valid row before the split-level step (v2.2's EC), with what that step reads."""

    result: TokenResult
    log_name: str
    t0_us: int
    states: FloatArray  # (41, 11) the agent's simulated states


class TokenError(Exception):
    """A token that cannot be scored; the message is safe to show to the submitting team."""


def _log() -> "logging.Logger":
    """Return the organisers' log; logging (1 ms of a score's start-up) loads where a cache is not built."""
    import logging

    return logging.getLogger(__name__)


def split_content_hash(split_dir: Path) -> str:
    """Return a hash over (token, scene file hash) of the split in token order, and over its stage mapping where
    it has one (a two-stage split's groups and weights follow it)."""
    from scorer.two_stage.split import MAPPING_FILE  # the two-stage code loads only where it is used

    digest = hashlib.sha256()
    for token, path in scene_paths(split_dir).items():
        digest.update(f"{token}:{scene_file_hash(path)}\n".encode())
    mapping = Path(split_dir) / MAPPING_FILE
    if mapping.is_file():
        digest.update(f"{MAPPING_FILE}:{hashlib.sha256(mapping.read_bytes()).hexdigest()}\n".encode())
    return digest.hexdigest()


def _build_and_save(
    scenes: Sequence[Scene], cache_dir: Path, versions: Sequence[str]
) -> list[dict[str, MetricCache]]:
    caches = build_cache_batch(scenes, [get_version(name) for name in versions])
    for scene_caches in caches:
        save_caches(scene_caches, cache_dir)
    return caches


def build_missing_caches(
    paths: Sequence[Path], cache_dir: Path, versions: Sequence[str]
) -> tuple[dict[str, dict[str, MetricCache]], dict[str, Exception]]:
    """Build and save whatever the cache lacks of `versions` for the scenes at `paths`, in batches.

    Return the caches built, by scene file name, and the error of each scene that failed, by file name:
    a batch that fails is built again scene by scene, so an error names its scene and the others go on.
    A version that shares another's cache has that one built (`cache_source`).
    """
    versions = list(dict.fromkeys(cache_source(version) for version in versions))
    built: dict[str, dict[str, MetricCache]] = {}
    errors: dict[str, Exception] = {}
    lacking: dict[tuple[str, ...], list[tuple[str, Scene]]] = {}  # scenes grouped by what they lack
    for path in paths:
        try:
            token, scene_hash = path.name.split(".")[0], scene_file_hash(path)
            # Read whole, not judged by the index: a damaged file is rebuilt.
            stored = load_caches(cache_dir, versions, token, scene_hash)
            missing = tuple(version for version in versions if version not in stored)
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
                log = _log()
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
    # Batches as even as can be, as many as the workers or a multiple: no worker is left with a short one.
    count = -(-len(paths) // CACHE_BATCH_SIZE)
    count += -count % max(workers, 1)
    bounds = [len(paths) * index // count for index in range(count + 1)] if count else []
    tasks = [
        (tuple(paths[start:end]), Path(cache_dir), tuple(versions))
        for start, end in itertools.pairwise(bounds)
        if end > start
    ]
    failures: dict[str, str] = {}
    results: Iterator[tuple[int, dict[str, str]]]
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor  # a one-process run never pays its import

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
    _log().warning("token %s: metric cache not built: %s: %s", token, type(error).__name__, error)
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


def token_results(
    caches: Sequence[MetricCache],
    seed: int | None,
    scores: ProposalScores,
    version: MetricVersion,
    start: int = 0,
) -> list[TokenResult]:
    """Return the agent's rows of `caches`, whose token b is row `start` + b of `scores`, each token scored alone
    (v2.2: filtered, EC undefined). A column's values are read from the scores at once, not value by value, and
    v2's row scores are formed at once (`extended_scores`)."""
    columns = [column for column in version.result_columns if column in ROW_COLUMNS]
    stop = start + len(caches)
    values = zip(*(getattr(scores, column)[start:stop, 1].tolist() for column in columns), strict=True)
    agents = [dict(zip(columns, row, strict=True)) for row in values]
    if version.two_frame_extended_comfort_weight is None:
        return [
            TokenResult(token=cache.token, seed=seed, valid=True, metrics=agent)
            for cache, agent in zip(caches, agents, strict=True)
        ]
    filtered_rows = [
        _human_filtered(cache, agent, version) for cache, agent in zip(caches, agents, strict=True)
    ]
    row_scores = extended_scores([_scored_columns(*row, version) for row in filtered_rows], version)
    results = []
    for cache, (metrics, detail), score in zip(caches, filtered_rows, row_scores, strict=True):
        metrics["score"] = score
        results.append(TokenResult(token=cache.token, seed=seed, valid=True, metrics=metrics, detail=detail))
    return results


def _human_filtered(
    cache: MetricCache, agent: dict[str, float], version: MetricVersion
) -> tuple[dict[str, float], dict[str, Any]]:
    """Return a v2 row's columns `agent` after the human filter, EC undefined, and the detail saying how the
    filter went; its score is formed afterwards (`extended_scores`)."""
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
    return metrics, detail


def _scored_columns(
    metrics: Mapping[str, float], detail: Mapping[str, Any], version: MetricVersion
) -> Mapping[str, float]:
    """Return the columns a row's score is formed from: its own, or, where the version's score ignores the human
    filter (before NAVSIM's fix of its issue 151, `human_filter_rescores`), the agent's before it, with the
    row's EC (docs/engine.md, "v2.2-prefix")."""
    before = detail.get("human_filter", {}).get("agent_before")
    if version.human_filter_rescores or before is None:
        return metrics
    return {**before, "two_frame_extended_comfort": metrics["two_frame_extended_comfort"]}


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
    """Return v2's final score of one row (`extended_scores`)."""
    return extended_scores([metrics], version)[0]


def extended_scores(rows: Sequence[Mapping[str, float]], version: MetricVersion) -> list[float]:
    """Return v2's final score of each row (`compute_final_scores`): the multipliers' product times the weighted
    mean of EP, TTC, LK, HC and EC, where an undefined EC (NaN) drops out with its weight (/16 or /14).

    The rows with EC and those without differ in their weights, so each kind is aggregated in one call; a
    column of rows is aggregated to the bits of each row alone (the weighted sum runs over the rows' few
    metrics in order either way)."""
    config = version.evaluation
    two_frame = np.array([row["two_frame_extended_comfort"] for row in rows], dtype=np.float64)
    defined = ~np.isnan(two_frame)
    multipliers = np.array(
        [[row[RESULT_COLUMN_OF_ROW[name]] for row in rows] for name in config.multiplier_rows],
        dtype=np.float64,
    ).reshape(len(config.multiplier_rows), len(rows))
    weighted = np.array(
        [[row[RESULT_COLUMN_OF_ROW[name]] for row in rows] for name in config.weights]
        + [np.where(defined, two_frame, 0.0)],
        dtype=np.float64,
    )
    scores = np.empty(len(rows))
    for with_two_frame in (True, False):
        rows_of_kind = defined == with_two_frame
        two_frame_weight = version.two_frame_extended_comfort_weight if with_two_frame else 0.0
        weights = np.array([*config.weights.values(), two_frame_weight])
        scores[rows_of_kind] = aggregate(multipliers[:, rows_of_kind], weighted[:, rows_of_kind], weights)
    return scores.tolist()


def simulate_agents(caches: Sequence[MetricCache], poses: Sequence[FloatArray]) -> FloatArray:
    """Return the agents' simulated states (B, 41, 11), one trajectory per cache: what every metric version
    scores, since the simulation depends on the poses and the scene's ego alone. Raises ValueError when a
    simulation diverges."""
    initial = np.stack([initial_state(cache.ego) for cache in caches])
    t0_us = np.array([cache.t0_us for cache in caches], dtype=np.int64)
    return simulate(agent_references(initial, t0_us, np.stack(poses)), initial)


def score_simulated(
    caches: Sequence[MetricCache], states: FloatArray, version: MetricVersion
) -> ProposalScores:
    """Return the scores (B, 2) of [PDM-Closed, agent] per token, as the devkit scores them: proposal 0 is the
    cached PDM-Closed reference (it sets the progress normaliser), proposal 1 the agent's simulated states."""
    by_token = {cache.token: token_states for cache, token_states in zip(caches, states, strict=True)}
    return score_simulated_versions({version.name: caches}, [by_token], [version])[version.name]


def score_simulated_versions(
    caches: Mapping[str, Sequence[MetricCache]],
    states: Sequence[Mapping[str, FloatArray]],
    versions: Sequence[MetricVersion],
) -> dict[str, ProposalScores]:
    """Return per version the scores (`score_simulated`) of the tokens of `caches[version.name]` under each seed,
    whose agents' simulated states (41, 11) `states[seed]` holds by token; each version's and seed's as it gets
    them alone. The scores (S·B, 2) are seed-major: row s·B + b is token b under seed s.

    The seeds of a token are measured together, as more proposals of it (a proposal's measures do not depend on
    the others it is measured with, `ProposalMeasures`): what reads the scene alone (its map, observation and
    centerline batches) is built once for every seed. Each seed's agent is then scored with the token's
    reference alone, every seed in one `score_measures` call (its tokens are scored as if alone).

    Versions that hold the same centerlines and routes for every token (PDM-Closed's, which every version
    shares) are measured in one `measure_alike` call: what reads the map and the ego alone (the ego boxes,
    their areas, DAC, progress) once for all of them, and what reads the observation once per way of
    observing (`observation_key`: v1.0 and v1.1 observe alike, v2.2 drops tracks on the ego). Versions that
    read one cache and score it with the same settings (v2.2 and v2.2-prefix, which differ in how a row's score
    is formed from these, `token_results`) get the scores of one computation.
    """
    first_alike: dict[tuple[object, ...], MetricVersion] = {}
    scored_as = {
        version.name: first_alike.setdefault(
            (cache_source(version.name), version.evaluation, version.reactive_traffic), version
        )
        for version in versions
    }
    distinct = list(first_alike.values())
    scores: dict[str, ProposalScores] = {
        version.name: _score_reacting(
            [cache for _ in states for cache in caches[version.name]],
            [seed_states[cache.token] for seed_states in states for cache in caches[version.name]],
            version,
        )
        for version in distinct
        if version.reactive_traffic is not None
    }
    groups: dict[tuple[object, ...], list[MetricVersion]] = {}
    for version in distinct:
        if version.reactive_traffic is not None:
            continue
        inputs = tuple(
            (cache.token, cache.centerline.tobytes(), cache.route_lane_ids) for cache in caches[version.name]
        )
        groups.setdefault(inputs, []).append(version)
    for group in groups.values():
        held = caches[group[0].name]  # alike maps, centerlines and routes: any version's caches give them
        # One list per way of observing, so that the versions observing alike pass the same objects.
        observed: dict[ObservationKey, list[Observation]] = {}
        for version in group:
            if observation_key(version) not in observed:
                observed[observation_key(version)] = [cache.observation for cache in caches[version.name]]
        measured = measure_alike(
            np.stack([np.stack([seed_states[cache.token] for seed_states in states]) for cache in held]),
            [observed[observation_key(version)] for version in group],
            [cache.drivable_map for cache in held],
            [cache.centerline[:, :2] for cache in held],
            [cache.route_lane_ids for cache in held],
            [MeasureSettings.of(version.evaluation) for version in group],
        )
        comfort: list[tuple[FloatArray, BoolArray]] = []  # v1's, shared where references agree
        for version, agents in zip(group, measured, strict=True):
            version_caches = caches[version.name]
            reference = join_measures([_reference_measures(cache) for cache in version_caches], axis=0)
            seeds = [join_measures([reference, agents.proposal(seed)]) for seed in range(len(states))]
            joined = join_measures(seeds, axis=0)
            comfortable = None
            if "comfortable" in version.evaluation.weights:
                comfortable = comfort_of(joined.comfort_series, comfort)
            pasts = [cache.past_states for cache in version_caches] * len(states)
            scores[version.name] = score_measures(joined, version.evaluation, pasts, comfortable)
    return {name: scores[version.name] for name, version in scored_as.items()}


def _reference_measures(cache: MetricCache) -> ProposalMeasures:
    if cache.reference_measures is None:
        raise ValueError(f"{cache.token}: a reactive version's cache holds no reference measures")
    return cache.reference_measures


def _score_reacting(
    caches: Sequence[MetricCache], states: Sequence[FloatArray], version: MetricVersion
) -> ProposalScores:
    """Return the scores (B, 2) of [PDM-Closed, agent] per cache under reactive traffic, `states` (41, 11) being
    the agent's of each: the vehicles react to the agent's simulated states, and both proposals are measured
    against them (`pdm_score` passes the one traffic simulation to the scorer for both)."""
    from scorer.reactive.observation import reacting_observation  # only reactive versions need it (start-up)

    config = version.reactive_traffic
    if config is None:
        raise ValueError(f"{version.name} has no reactive traffic")
    observations, proposals = [], []
    for cache, agent in zip(caches, states, strict=True):
        if cache.starting_traffic is None or cache.reference_states is None:
            raise ValueError(f"{cache.token}: the cache of {version.name} holds no reactive traffic")
        observations.append(reacting_observation(cache.starting_traffic, cache.observation, agent, config))
        proposals.append(np.stack([cache.reference_states, agent]))
    measured = measure_alike(
        np.stack(proposals),
        [observations],
        [cache.drivable_map for cache in caches],
        [cache.centerline[:, :2] for cache in caches],
        [cache.route_lane_ids for cache in caches],
        [MeasureSettings.of(version.evaluation)],
    )[0]
    return score_measures(measured, version.evaluation, [cache.past_states for cache in caches])


def score_against_references(
    caches: Sequence[MetricCache], poses: Sequence[FloatArray], version: MetricVersion
) -> tuple[FloatArray, ProposalScores]:
    """Return the agents' simulated states (B, 41, 11) and their scores (`score_simulated`)."""
    states = simulate_agents(caches, poses)
    return states, score_simulated(caches, states, version)


def _rows_of_simulated(
    caches: Mapping[str, Sequence[MetricCache]],
    states: Mapping[tuple[int | None, str], FloatArray],
    failed: Mapping[tuple[int | None, str], str],
    versions: Sequence[MetricVersion],
    seeds: Sequence[int | None],
) -> dict[tuple[int | None, str], list[TokenResult | ScoredToken]]:
    """Return per (seed, version) the rows of the tokens of `caches[version.name]` that the seed simulated, by
    their simulated states or errors by (seed, token) (`_simulated`): an invalid row where the simulation
    diverged, the others scored in one batch for every seed (`score_simulated_versions`), each seed's in the
    order of the caches.

    A token that a seed lacks (no prediction, or a diverged simulation) is measured under that seed on another
    seed's states, whose row is left out: every token has a proposal per seed in the batch."""
    rows: dict[tuple[int | None, str], list[TokenResult | ScoredToken]] = {}
    kept: dict[str, list[MetricCache]] = {}
    for version in versions:
        held = caches[version.name]
        traffic_errors = {
            cache.token: f"scoring failed: reactive traffic: {cache.starting_traffic.failure}"
            for cache in held
            if cache.starting_traffic is not None and cache.starting_traffic.failure is not None
        }
        for seed in seeds:
            errors = {
                cache.token: failed[seed, cache.token] for cache in held if (seed, cache.token) in failed
            }
            errors |= {
                token: error
                for token, error in traffic_errors.items()
                if (seed, token) in states or (seed, token) in failed
            }
            rows[seed, version.name] = [
                TokenResult(cache.token, seed, False, error=errors[cache.token])
                for cache in held
                if cache.token in errors
            ]
        kept[version.name] = [
            cache
            for cache in held
            if cache.token not in traffic_errors and any((seed, cache.token) in states for seed in seeds)
        ]
    stand_in: dict[str, FloatArray] = {}
    for (_, token), token_states in states.items():
        stand_in.setdefault(token, token_states)
    by_seed = [
        {token: states.get((seed, token), other) for token, other in stand_in.items()} for seed in seeds
    ]
    measured = [version for version in versions if kept[version.name]]
    scores = score_simulated_versions(kept, by_seed, measured)
    for version in measured:
        version_kept = kept[version.name]
        for at, seed in enumerate(seeds):
            results = token_results(version_kept, seed, scores[version.name], version, at * len(version_kept))
            rows[seed, version.name] += [
                ScoredToken(result, cache.log_name, cache.t0_us, states[seed, cache.token])
                for cache, result in zip(version_kept, results, strict=True)
                if (seed, cache.token) in states
            ]
    return rows


def _simulated(
    keys: Sequence[Key], caches: Sequence[MetricCache], poses: Sequence[FloatArray]
) -> tuple[dict[Key, FloatArray], dict[Key, str]]:
    """Return the simulated states of each trajectory (named by its key: a token, or a token and seed), and the
    error of each one that diverged: one diverging trajectory must not fail its neighbours, so a batch that
    diverges is simulated trajectory by trajectory."""
    if not keys:
        return {}, {}
    try:
        return dict(zip(keys, simulate_agents(caches, poses), strict=True)), {}
    except ValueError as error:
        if len(keys) == 1:
            return {}, {keys[0]: f"scoring failed: {error}"}
    states: dict[Key, FloatArray] = {}
    failed: dict[Key, str] = {}
    for key, cache, pose in zip(keys, caches, poses, strict=True):
        one, error_of_one = _simulated([key], [cache], [pose])
        states |= one
        failed |= error_of_one
    return states, failed


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
    """Return one result per token (all tokens of the split by default) under one version (`score_versions`)."""
    return score_versions(split_dir, cache_dir, predictions, [version], tokens, seed, progress, context)[
        version
    ]


def score_versions(
    split_dir: Path,
    cache_dir: Path,
    predictions: Mapping[str, object],
    versions: Sequence[str],
    tokens: Sequence[str] | None = None,
    seed: int | None = None,
    progress: Callable[[int], None] | None = None,
    context: Sequence[str] = (),
) -> dict[str, list[TokenResult]]:
    """Return, per metric version, one result per token of one seed's `predictions` (`score_seeds`)."""
    return score_seeds(split_dir, cache_dir, {seed: predictions}, versions, tokens, progress, context)


def score_seeds(
    split_dir: Path,
    cache_dir: Path,
    seeds: Mapping[int | None, Mapping[str, object]],
    versions: Sequence[str],
    tokens: Sequence[str] | None = None,
    progress: Callable[[int], None] | None = None,
    context: Sequence[str] = (),
    scenes: "SceneFiles | None" = None,
) -> dict[str, list[TokenResult]]:
    """Return, per metric version, one result per token (all tokens of the split by default) and seed, seed by
    seed in the order of `seeds` (seed -> predictions), building whatever the cache lacks (`score_rows`), with
    two-frame comfort between adjacent frames of a log.

    `context` tokens are scored too, under a version with two-frame comfort, for their rows to pair with
    `tokens` of the same seed (`pairing_contexts`), and are not returned. `scenes` are the split's scene files
    when the caller knows them (a worker's mirror of a stored split); by default `split_dir`'s.
    """
    metric_versions = [get_version(version) for version in versions]
    scenes = scenes or SceneFiles(scene_paths(split_dir))
    tokens = list(scenes.paths) if tokens is None else list(tokens)
    if all(version.two_frame_extended_comfort_weight is None for version in metric_versions):
        context = ()
    requested = set(tokens)
    scored_tokens = tokens + [token for token in dict.fromkeys(context) if token not in requested]
    results = score_rows(split_dir, cache_dir, seeds, versions, scored_tokens, progress, scenes)
    order = {token: index for index, token in enumerate(tokens)}
    joined: dict[str, list[TokenResult]] = {version.name: [] for version in metric_versions}
    for seed in seeds:
        for version in metric_versions:
            scored, rows = split_scored(results[seed, version.name])
            rows += join_two_frame_comfort(scored, version) if scored else []
            joined[version.name] += sorted(
                (row for row in rows if row.token in order), key=lambda row: order[row.token]
            )
    return joined


ScoredRows = dict[tuple[int | None, str], list[TokenResult | ScoredToken]]


class SceneFiles(NamedTuple):
    """A split's scene files as scoring reads them: token -> file, and, for a split whose files are fetched
    on demand (a worker's mirror of a stored split), each file's sha256 as registered and how to fetch files.
    A token's cache is then found by its registered sha256, and only the scenes of caches to build are
    fetched (`fetch`, given their tokens): a token with a valid cache is scored without its scene file."""

    paths: Mapping[str, Path]
    hashes: Mapping[str, str] | None = None
    fetch: Callable[[Sequence[str]], object] | None = None
    # Token -> its cache file's bytes when the caller holds them (fetched from an object store): read instead
    # of the cache directory's file.
    caches: Mapping[str, bytes] = MappingProxyType({})

    def file_hash(self, token: str) -> str:
        """Return the sha256 of the token's scene file (the cache key): registered, or hashed from the file."""
        return self.hashes[token] if self.hashes is not None else scene_file_hash(self.paths[token])


def score_rows(
    split_dir: Path,
    cache_dir: Path,
    seeds: Mapping[int | None, Mapping[str, object]],
    versions: Sequence[str],
    tokens: Sequence[str],
    progress: Callable[[int], None] | None = None,
    scenes: SceneFiles | None = None,
) -> ScoredRows:
    """Return, per (seed, version), the rows of `tokens` before the split-level step (v2.2's EC): a ScoredToken
    per scored token, an invalid TokenResult per other. A token's caches are read once for every seed, and
    each trajectory is simulated once for every version; a chunk's trajectories of every seed go through one
    simulation. `scenes` as `score_seeds` takes them."""
    metric_versions = [get_version(version) for version in versions]
    scenes = scenes or SceneFiles(scene_paths(split_dir))
    results: ScoredRows = {(seed, version.name): [] for seed in seeds for version in metric_versions}
    for start in range(0, len(tokens), CHUNK_SIZE):
        chunk = tokens[start : start + CHUNK_SIZE]
        # A chunk's cache reading, measures and rows allocate many short-lived, acyclic objects.
        with collector_paused():
            scored = _score_chunk(scenes, Path(cache_dir), seeds, metric_versions, chunk)
        for key, scored_rows in scored.items():
            results[key] += scored_rows
        if progress is not None:
            progress(len(chunk) * len(seeds))
    return results


def split_scored(rows: Sequence[TokenResult | ScoredToken]) -> tuple[list[ScoredToken], list[TokenResult]]:
    """Return the scored rows and the invalid ones of `score_rows`' rows."""
    return (
        [row for row in rows if isinstance(row, ScoredToken)],
        [row for row in rows if isinstance(row, TokenResult)],
    )


def _score_chunk(
    scenes: SceneFiles,
    cache_dir: Path,
    seeds: Mapping[int | None, Mapping[str, object]],
    versions: Sequence[MetricVersion],
    tokens: Sequence[str],
) -> dict[tuple[int | None, str], list[TokenResult | ScoredToken]]:
    """Score a chunk of tokens under `versions` and `seeds`, by (seed, version): each token's caches loaded once
    (or built, every version at once), every seed's trajectories simulated together, then measured and scored
    per version, every seed at once (`_rows_of_simulated`)."""
    paths = scenes.paths
    rows: dict[tuple[int | None, str], list[TokenResult | ScoredToken]] = {
        (seed, version.name): [] for seed in seeds for version in versions
    }
    poses: dict[tuple[int | None, str], FloatArray] = {}
    for seed, predictions in seeds.items():
        for token in tokens:
            try:
                if token not in paths:
                    raise TokenError("token is not part of the split")
                if token not in predictions:
                    raise TokenError("no prediction for this token")
                poses[seed, token] = _checked_poses(predictions[token])
            except TokenError as error:
                for version in versions:
                    rows[seed, version.name].append(TokenResult(token, seed, False, error=str(error)))
    posed = {token for _, token in poses}
    needed = list(dict.fromkeys(token for token in tokens if token in posed))  # each seed's tokens in order
    caches: dict[str, dict[str, MetricCache]] = {version.name: {} for version in versions}
    unbuilt: list[str] = []
    scene_hashes = {token: scenes.file_hash(token) for token in needed}
    for token in needed:
        names = [version.name for version in versions]
        loaded = load_caches(cache_dir, names, token, scene_hashes[token], scenes.caches.get(token))
        for name in loaded:
            caches[name][token] = loaded[name]
        if len(loaded) < len(versions):
            unbuilt.append(token)
    # Every version at once: one PDM-Closed unroll serves them all.
    together = cached_together(version.name for version in versions)
    if unbuilt and scenes.fetch is not None:
        scenes.fetch(unbuilt)
    built, errors = build_missing_caches([paths[token] for token in unbuilt], cache_dir, together)
    for token in unbuilt:
        name = paths[token].name
        missing = [version for version in versions if token not in caches[version.name]]
        # Built here, or meanwhile by another process (then build_missing_caches found it and built nothing):
        # the file is read once for whatever was not built here.
        found = dict(built.get(name, {}))
        unfound = [version.name for version in missing if version.name not in found]
        if unfound:
            found |= load_caches(cache_dir, unfound, token, scene_hashes[token])
        for version in missing:
            if version.name in found:
                caches[version.name][token] = found[version.name]
                continue
            cause = errors.get(name, RuntimeError("the cache file was not written"))
            text = _build_error_text(token, cause)
            for seed in seeds:
                if (seed, token) in poses:
                    rows[seed, version.name].append(TokenResult(token, seed, False, error=text))
    # Any version's cache holds the token's ego and start time for its simulation.
    first_cache: dict[str, MetricCache] = {}
    for token in needed:
        holding = [caches[version.name][token] for version in versions if token in caches[version.name]]
        if holding:
            first_cache[token] = holding[0]
    simulated = [key for key in poses if key[1] in first_cache]
    states, failed = _simulated(
        simulated, [first_cache[token] for _, token in simulated], [poses[key] for key in simulated]
    )
    held: dict[str, list[MetricCache]] = {
        version.name: [caches[version.name][token] for token in needed if token in caches[version.name]]
        for version in versions
    }
    for key, version_rows in _rows_of_simulated(held, states, failed, versions, list(seeds)).items():
        rows[key] += version_rows
    return rows


def summarize(results: Sequence[TokenResult], columns: Sequence[str] = METRIC_COLUMNS) -> dict[str, float]:
    """Return the mean of every column over tokens, an unscored token counting 0, and the failed count.

    An undefined value (v2.2's EC without an adjacent frame) is left out of its column's mean, as the
    devkit's average row skips NaN; a column undefined everywhere is NaN.
    """
    summary = {column: defined_mean([r.metrics.get(column, 0.0) for r in results]) for column in columns}
    summary["tokens"] = float(len(results))
    summary["failed"] = float(sum(not r.valid for r in results))
    return summary


def _in_log_order(frames: Sequence[tuple[str, str, int]]) -> list[list[int]]:
    """Return the indices of `frames` (token, log name, t0 in us) per log, in the order the devkit gives a log's
    frames for EC (`infer_start_adjacent_mapping`): original frames only (a 17-character token is synthetic),
    by start time in float seconds (`timestamp_us * 1e-6`), ties by token (pandas' sort is not stable)."""
    by_log: dict[str, list[int]] = {}
    for index, (token, log_name, _) in enumerate(frames):
        if not is_synthetic(token):
            by_log.setdefault(log_name, []).append(index)
    for members in by_log.values():
        members.sort(key=lambda index: (frames[index][2] * 1e-6, frames[index][0]))
    return list(by_log.values())


def _adjacent(earlier: tuple[str, str, int], later: tuple[str, str, int]) -> bool:
    """Whether two frames of a log in that order are close enough in time for EC to pair them."""
    return abs(later[2] * 1e-6 - earlier[2] * 1e-6) <= ADJACENT_GAP_S


def adjacent_pairs(scored: Sequence[ScoredToken]) -> dict[int, int]:
    """Return, for each row that pairs with the row before it in its log (`_in_log_order`), that row."""
    frames = [(item.result.token, item.log_name, item.t0_us) for item in scored]
    return {
        current: previous
        for members in _in_log_order(frames)
        for previous, current in itertools.pairwise(members)
        if _adjacent(frames[previous], frames[current])
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
    frames = [(token, log_name, t0_us) for token, (log_name, t0_us) in starts.items()]
    position = {
        frames[index][0]: (members, at)
        for members in _in_log_order(frames)
        for at, index in enumerate(members)
    }
    contexts = []
    for group in groups:
        context: dict[str, None] = {}
        for token in group:
            members, at = position.get(token, ([], 0))
            earlier = at - 1
            while earlier >= 0 and _adjacent(frames[members[earlier]], frames[members[at]]):
                if frames[members[earlier]][0] not in group:
                    context[frames[members[earlier]][0]] = None
                earlier -= 1
        contexts.append(list(context))
    return contexts


def join_two_frame_comfort(
    scored: Sequence[ScoredToken], version: MetricVersion, pairs: Sequence[tuple[str, str]] | None = None
) -> list[TokenResult]:
    """Return the rows with v2's two-frame extended comfort (EC) and the final score, NaN (weight dropped) where
    a row has no EC.

    `pairs` (current token, previous token) are the frames to compare, as a two-stage split's mapping gives
    them (orig and prev, now2 and prev2 of each pair): each pair's EC goes to both its rows, as the two-stage
    aggregator writes it. Without them, one-stage: each row pairs with the adjacent earlier frame of its log
    scored in the same run and seed (`adjacent_pairs`), and only the later row gets EC.

    Where the devkit pairs two frames and then fails on them (start times equal, 0.55 s apart to the float, or
    under 0.05 s apart, a partner not scored), EC is undefined and the row's detail says why.
    """
    if version.two_frame_extended_comfort_weight is None:
        return [item.result for item in scored]
    details: dict[int, dict[str, Any]] = {}
    receivers: dict[int, list[int]] = {}  # a pair's current row -> the rows that get its EC
    if pairs is None:
        index_pairs = list(adjacent_pairs(scored).items())
        for index, previous in index_pairs:
            details[index] = {"previous_token": scored[previous].result.token}
            receivers[index] = [index]
    else:
        at = {item.result.token: index for index, item in enumerate(scored)}
        index_pairs = []
        for current_token, previous_token in pairs:
            for token, partner, key in (
                (current_token, previous_token, "previous_token"),
                (previous_token, current_token, "current_token"),
            ):
                if token in at:
                    details[at[token]] = {key: partner}
                    if partner not in at:
                        details[at[token]]["undefined"] = f"its partner {partner} was not scored"
            if current_token in at and previous_token in at:
                index_pairs.append((at[current_token], at[previous_token]))
                receivers[at[current_token]] = [at[current_token], at[previous_token]]
    computed: list[tuple[int, int, int]] = []  # (row, previous row, steps)
    for index, previous in index_pairs:
        try:
            computed.append((index, previous, overlap_steps(scored[index].t0_us, scored[previous].t0_us)))
        except ValueError as error:
            for row in receivers[index]:
                details[row]["undefined"] = f"the official code pairs this frame and then fails: {error}"
    values: dict[int, tuple[float, dict[str, float]]] = {}
    if computed:
        rows, previous_rows, steps = (list(column) for column in zip(*computed, strict=True))
        comfort = two_frame_extended_comfort(
            np.stack([scored[row].states for row in rows]),
            np.stack([scored[row].states for row in previous_rows]),
            steps,
        )
        for position, row in enumerate(rows):
            value = (
                float(comfort.value[position]),
                dict(zip(FEATURES, comfort.rms[position].tolist(), strict=True)),
            )
            values |= dict.fromkeys(receivers[row], value)
    results = []
    for index, item in enumerate(scored):
        if index not in details:
            results.append(item.result)
            continue
        metrics, detail = dict(item.result.metrics), dict(item.result.detail)
        if index in values:
            metrics["two_frame_extended_comfort"], rms = values[index]
            details[index]["rms"] = rms
            metrics["score"] = extended_score(_scored_columns(metrics, detail, version), version)
        detail["two_frame_extended_comfort"] = details[index]
        results.append(replace(item.result, metrics=metrics, detail=detail))
    return results
