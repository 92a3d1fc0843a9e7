"""A two-stage submission scored end to end (docs/engine.md, "Two-stage EPDMS"): every submitted token of both
stages under a two-stage metric version (reactive traffic), two-frame comfort between the pairs of the split's
stage mapping (orig and prev, now2 and prev2), each token's start point and submitted endpoint, then the
aggregation, seed by seed.

As the official `run_pdm_score` does, the rows are the submission's: stage one's tokens in submission order,
then stage two's; a token is scored whatever the mapping says of it, and the aggregation says what it makes of
tokens outside the mapping or missing from it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from scorer.evaluate import (
    CHUNK_SIZE,
    ScoredRows,
    ScoredToken,
    TokenResult,
    join_two_frame_comfort,
    score_rows,
    split_scored,
)
from scorer.geometry import FloatArray
from scorer.scene import SceneFormatError, load_scene, scene_paths
from scorer.submission import TwoStageSubmission, load_submission, load_two_stage_submission
from scorer.trajectory import initial_state
from scorer.two_stage.aggregate import TwoStageResult, TwoStageToken, aggregate_two_stage
from scorer.two_stage.split import TwoStageSplit, load_two_stage_split
from scorer.two_stage.weights import global_endpoints
from scorer.versions import MetricVersion, get_version

Predictions = dict[str, FloatArray]
UNKNOWN_POSE = (math.nan, math.nan, math.nan)


def comfort_pairs(split: TwoStageSplit) -> list[tuple[str, str]]:
    """Return the (current, previous) frames whose two-frame comfort the official aggregator computes: each
    entry's (orig, prev) and each of its pairs (now2, prev2); none for a null mapping."""
    return [pair for group in split.groups or () for pair in ((group.original, group.previous), *group.pairs)]


def submitted_rows(submission: TwoStageSubmission, seed: int) -> Predictions:
    """Return one seed's predictions in the official row order: stage one's, then stage two's (a token submitted
    in both stages is scored once, with its stage-one poses)."""
    rows = dict(submission.first_stage[seed])
    rows |= {token: poses for token, poses in submission.second_stage[seed].items() if token not in rows}
    return rows


def predictions_per_seed(content: bytes, filename: str, version: str) -> list[Predictions]:
    """Return each seed's token -> poses that `version` scores in a submission file: under a two-stage version
    both stages' (`submitted_rows`), else the one-stage file's. Raises SubmissionError for a file that is not
    a submission of the version's kind."""
    if not get_version(version).two_stage:
        return list(load_submission(content, filename).seeds)
    loaded = load_two_stage_submission(content, filename)
    return [submitted_rows(loaded, seed) for seed in range(len(loaded.first_stage))]


def _score_part(task: tuple[Path, Path, dict[int | None, Predictions], str, list[str]]) -> ScoredRows:
    split_dir, cache_dir, seeds, version, tokens = task
    return score_rows(split_dir, cache_dir, seeds, [version], tokens)


def _scored_in_parts(
    split_dir: Path,
    cache_dir: Path,
    seeds: dict[int | None, Predictions],
    version: str,
    progress: Callable[[int], None] | None,
    workers: int,
) -> ScoredRows:
    """Return `score_rows` of every submitted token, in `workers` processes over disjoint parts of the tokens
    (a token's traffic and scores do not depend on any other token; the pairs are joined afterwards)."""
    tokens = list(dict.fromkeys(token for predictions in seeds.values() for token in predictions))
    if workers <= 1:
        return score_rows(split_dir, cache_dir, seeds, [version], tokens, progress)
    from concurrent.futures import (
        ProcessPoolExecutor,
        as_completed,
    )  # a one-process run never pays its import

    size = max(1, min(CHUNK_SIZE, math.ceil(len(tokens) / (4 * workers))))
    parts = [tokens[start : start + size] for start in range(0, len(tokens), size)]
    merged: ScoredRows = {(seed, version): [] for seed in seeds}
    with ProcessPoolExecutor(max_workers=workers) as executor:
        futures = {
            executor.submit(_score_part, (split_dir, cache_dir, seeds, version, part)): len(part)
            for part in parts
        }
        for future in as_completed(futures):
            for key, rows in future.result().items():
                merged[key] += rows
            if progress is not None:
                progress(futures[future] * len(seeds))
    return merged


def start_pose(path: Path | None) -> tuple[float, float, float]:
    """Return the ego rear axle at t = 0 (x, y, heading) as the metric cache's EgoState reports it, read from the
    scene file of a token that did not score; unknown where the scene cannot be read."""
    if path is None:
        return UNKNOWN_POSE
    try:
        x, y, heading = initial_state(load_scene(path).current_frame.ego)[:3].tolist()
    except (SceneFormatError, OSError):
        return UNKNOWN_POSE
    return x, y, heading


def two_stage_tokens(
    rows: Sequence[TokenResult | ScoredToken],
    predictions: Predictions,
    version: MetricVersion,
    pairs: Sequence[tuple[str, str]],
    paths: Mapping[str, Path],
    tokens: Sequence[str],
) -> list[TwoStageToken]:
    """Return `tokens`' results as the aggregation reads them, from one seed's `score_rows` rows of `tokens` and
    of the partners their pairs name (`pairs`: `comfort_pairs`): two-frame comfort by the mapping, each token's
    start point and its submitted endpoint."""
    scored, unscored = split_scored(rows)
    results: dict[str, TokenResult] = {row.token: row for row in unscored}
    results |= {row.token: row for row in join_two_frame_comfort(scored, version, pairs)}
    starts: Mapping[str, Sequence[float]] = {
        item.result.token: item.states[0, :3].tolist() for item in scored
    }
    start_poses = np.array([starts.get(token) or start_pose(paths.get(token)) for token in tokens])
    endpoints = global_endpoints(np.stack([predictions[token] for token in tokens]), start_poses)
    return [
        TwoStageToken(results[token], (start[0], start[1]), (end[0], end[1]))
        for token, start, end in zip(tokens, start_poses.tolist(), endpoints.tolist(), strict=True)
    ]


def score_two_stage_part(
    split_dir: Path,
    stages: TwoStageSplit,
    cache_dir: Path,
    seeds: Mapping[int | None, Predictions],
    version: str,
    tokens: Sequence[str],
    context: Sequence[str] = (),
) -> dict[int | None, list[TwoStageToken]]:
    """Return, per seed, the results of some `tokens` of a two-stage submission (every token's poses in `seeds`),
    scored beside the `context` tokens their mapping (`stages`, the split's) pairs them with for two-frame
    comfort (not returned). A part's results are those the whole submission gives its tokens: a token's
    traffic and scores depend on no other token, its comfort on its partner alone. `split_dir` need hold only
    the scenes of the tokens scored."""
    pairs = comfort_pairs(stages)
    requested = set(tokens)
    scored = score_rows(
        split_dir,
        cache_dir,
        seeds,
        [version],
        [*tokens, *(t for t in dict.fromkeys(context) if t not in requested)],
    )
    paths = scene_paths(split_dir)
    metric_version = get_version(version)
    return {
        seed: two_stage_tokens(scored[seed, version], predictions, metric_version, pairs, paths, tokens)
        for seed, predictions in seeds.items()
    }


def score_two_stage(
    split_dir: Path,
    cache_dir: Path,
    submission: TwoStageSubmission,
    version: str,
    progress: Callable[[int], None] | None = None,
    workers: int = 1,
) -> list[TwoStageResult]:
    """Return the two-stage EPDMS of each seed of `submission` on the two-stage split at `split_dir`, building
    whatever the cache lacks. Rows carry the seed as the one-stage scoring does: None for a single seed."""
    metric_version = get_version(version)
    if not metric_version.two_stage:
        raise ValueError(f"{version} is a one-stage metric version: it does not score a two-stage submission")
    split = load_two_stage_split(split_dir)
    count = len(submission.first_stage)
    seeds: dict[int | None, Predictions] = {
        (index if count > 1 else None): submitted_rows(submission, index) for index in range(count)
    }
    scored_rows = _scored_in_parts(Path(split_dir), Path(cache_dir), seeds, version, progress, workers)
    paths = scene_paths(split_dir)
    pairs = comfort_pairs(split)
    results = []
    for index, (seed, predictions) in enumerate(seeds.items()):
        tokens = two_stage_tokens(
            scored_rows[seed, version], predictions, metric_version, pairs, paths, list(predictions)
        )
        result = aggregate_two_stage(tokens, split)
        twice = [token for token in submission.first_stage[index] if token in submission.second_stage[index]]
        if twice:
            notes = [
                f"token {token} is in both stages' predictions: scored once, as stage one" for token in twice
            ]
            result = replace(result, official=False, notes=(*result.notes, *notes))
        results.append(result)
    return results
