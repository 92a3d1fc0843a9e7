"""Aggregating a complete run: per-token rows -> per-seed results -> summaries with multi-seed spread and a
bootstrap 95% interval, per (metric version, subset).

Means follow `scorer.evaluate.summarize`: every token of the subset counts, a token that could not be
scored counting 0, and the number of such tokens is reported.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from scorer.metrics.aggregation import defined_mean
from scorer.versions import ALL_RESULT_COLUMNS, get_version
from server.models import Result, Submission, Summary, TokenResultRow

BOOTSTRAP_SEED = 20240915  # fixed: the same rows always give the same interval
BOOTSTRAP_BATCH = 256


def bootstrap_cis(
    token_scores: np.ndarray, samples: int, seed: int = BOOTSTRAP_SEED
) -> list[tuple[float, float]]:
    """Return the percentile bootstrap 95% interval of the mean of each row of `token_scores` (series, tokens),
    resampling tokens.

    Every row gets the same resamples, drawn once: the draws depend only on the seed and the number of
    tokens, and a navtest-size draw (2000 x 12,000) costs more than the means it feeds.
    """
    series, count = token_scores.shape
    if count == 0:
        return [(float("nan"), float("nan"))] * series
    rng = np.random.default_rng(seed)
    means = np.empty((series, samples))
    for start in range(0, samples, BOOTSTRAP_BATCH):
        stop = min(start + BOOTSTRAP_BATCH, samples)
        drawn = rng.integers(0, count, size=(stop - start, count))
        for row, scores in enumerate(token_scores):  # a row at a time: (series, draws, tokens) sums otherwise
            means[row, start:stop] = scores[drawn].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5], axis=1)
    return [(float(lo), float(hi)) for lo, hi in zip(low, high, strict=True)]


@dataclass(frozen=True)
class _SeedRows:
    """A run's rows of one (metric version, seed) as arrays, in the order the database gave them."""

    position: dict[str, int]  # token -> its row
    # (rows + 1, ALL_RESULT_COLUMNS): a null value as NaN, every value of an invalid row 0; the last row, all 0
    # and invalid, stands for a token without a row (never scored: it counts as a failed token).
    values: np.ndarray
    valid: np.ndarray
    workers: np.ndarray  # (rows,) of str
    durations: np.ndarray  # (rows,)

    @classmethod
    def of(
        cls,
        tokens: Sequence[str],
        valid: np.ndarray,
        workers: np.ndarray,
        durations: np.ndarray,
        values: np.ndarray,
    ) -> _SeedRows:
        """Return the rows of `tokens`, each with its validity, worker, duration and values (ALL_RESULT_COLUMNS)."""
        valid = np.append(valid.astype(bool), False)
        values = np.concatenate([values, np.zeros((1, len(ALL_RESULT_COLUMNS)))])
        values[~valid] = 0.0
        position = dict(zip(tokens, range(len(tokens)), strict=True))
        return cls(position, values, valid, workers, durations)

    @classmethod
    def empty(cls) -> _SeedRows:
        """Return the rows of a (version, seed) without any: every token counts as failed."""
        return cls.of(
            [], np.zeros(0), np.zeros(0, dtype=object), np.zeros(0), np.zeros((0, len(ALL_RESULT_COLUMNS)))
        )

    def of_tokens(
        self, tokens: Sequence[str], columns: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the `columns` (indices into ALL_RESULT_COLUMNS) of `tokens`' rows, (tokens, columns), their
        validity, and the rows of those that have one."""
        missing = len(self.durations)
        at = np.array([self.position.get(token, missing) for token in tokens], dtype=np.intp)
        return self.values[np.ix_(at, columns)], self.valid[at], at[at < missing]


_ROW_COLUMNS = (
    TokenResultRow.metric_version,
    TokenResultRow.seed,
    TokenResultRow.token,
    TokenResultRow.valid,
    TokenResultRow.worker,
    TokenResultRow.duration_s,
)


def _seed_rows(session: Session, submission: Submission) -> dict[tuple[str, int], _SeedRows]:
    """Return (metric version, seed) -> the current run's rows: the columns the aggregation reads, not the
    rows' details. A navtest-size run has about 100,000: they are read as plain tuples (no ORM rows) and
    turned into one array per column."""
    query = select(*_ROW_COLUMNS, *(getattr(TokenResultRow, column) for column in ALL_RESULT_COLUMNS)).where(
        TokenResultRow.submission_id == submission.id, TokenResultRow.run == submission.run
    )
    columns = list(zip(*session.connection().execute(query).all(), strict=True))
    if not columns:
        return {}
    versions, seeds, tokens, valid, workers, durations = columns[: len(_ROW_COLUMNS)]
    # Null values become NaN.
    values = np.array(columns[len(_ROW_COLUMNS) :], dtype=object).astype(np.float64).T
    valid_array, worker_array = np.array(valid, dtype=bool), np.array(workers, dtype=object)
    duration_array = np.array(durations, dtype=np.float64)
    grouped: dict[tuple[str, int], list[int]] = defaultdict(list)
    for index, key in enumerate(zip(versions, seeds, strict=True)):
        grouped[key].append(index)
    return {
        key: _SeedRows.of(
            [tokens[index] for index in indices],
            valid_array[indices],
            worker_array[indices],
            duration_array[indices],
            values[indices],
        )
        for key, indices in grouped.items()
    }


def stored_value(value: float | None) -> float | None:
    """Return a value as a result column holds it: undefined (NaN: v2.2's EC without a pair, or a mean no token
    defines) or absent as null."""
    return None if value is None or math.isnan(value) else value


def aggregate_submission(
    session: Session,
    submission: Submission,
    subsets: dict[str, list[str]],
    engine_version: str,
    bootstrap_samples: int,
) -> None:
    """Replace the results and summaries of a submission with those of its current run's per-token rows, under
    its one-stage versions (a two-stage version's are written by server.runs._two_stage).

    The means are `scorer.evaluate.summarize`'s to the bit: the same values in the same order (the subset's),
    an unscored token 0 and an undefined value left out.
    """
    by_seed = _seed_rows(session, submission)
    session.execute(delete(Result).where(Result.submission_id == submission.id))
    session.execute(delete(Summary).where(Summary.submission_id == submission.id))
    versions = sorted({version for version, _ in by_seed if not get_version(version).two_stage})
    seeds = sorted({seed for _, seed in by_seed})
    if not versions:
        return
    unscored = _SeedRows.empty()
    for subset, tokens in subsets.items():
        per_version = {}
        for version in versions:
            columns = get_version(version).result_columns
            picked = np.array([ALL_RESULT_COLUMNS.index(column) for column in columns], dtype=np.intp)
            per_seed = []
            for seed in seeds:
                rows = by_seed.get((version, seed), unscored)
                values, valid, present = rows.of_tokens(tokens, picked)
                per_seed.append((values, valid))
                session.add(
                    seed_result(
                        submission,
                        version,
                        subset,
                        seed,
                        tokens=len(tokens),
                        failed=int(np.count_nonzero(~valid)),
                        engine_version=engine_version,
                        workers=set(rows.workers[present].tolist()),
                        duration_s=float(sum(rows.durations[np.sort(present)].tolist())),
                        means={column: defined_mean(values[:, at]) for at, column in enumerate(columns)},
                    )
                )
            per_version[version] = _by_column(per_seed, columns), [valid for _, valid in per_seed], columns
        # One resampling for every version: their seed-averaged token scores, one row each.
        token_scores = np.array([by_column["score"].mean(axis=0) for by_column, _, _ in per_version.values()])
        intervals = bootstrap_cis(token_scores.reshape(len(per_version), len(tokens)), bootstrap_samples)
        for (version, (by_column, validity, columns)), interval in zip(
            per_version.items(), intervals, strict=True
        ):
            session.add(_summary(submission.id, version, subset, by_column, validity, interval, columns))
    session.flush()


def seed_result(
    submission: Submission,
    version: str,
    subset: str,
    seed: int,
    *,
    tokens: int,
    failed: int,
    engine_version: str,
    workers: set[str],
    duration_s: float,
    means: Mapping[str, float | None],
    two_stage: dict[str, Any] | None = None,
) -> Result:
    """Return the Result of one seed of an entry: what it was scored from (engine, split, workers, time) and
    each column's value (`means`; undefined: null)."""
    return Result(
        submission_id=submission.id,
        metric_version=version,
        subset=subset,
        seed=seed,
        tokens=tokens,
        failed=failed,
        engine_version=engine_version,
        split_hash=submission.split.content_hash,
        workers=",".join(sorted(workers)),
        duration_s=duration_s,
        two_stage=two_stage,
        **{column: stored_value(mean) for column, mean in means.items()},
    )


def _by_column(
    per_seed: list[tuple[np.ndarray, np.ndarray]], columns: tuple[str, ...]
) -> dict[str, np.ndarray]:
    """Return column -> its values (seeds, tokens), unscored tokens as 0, from each seed's (values (tokens,
    columns), validity)."""
    return {
        column: np.stack([seed_values[:, at] for seed_values, _ in per_seed])
        for at, column in enumerate(columns)
    }


def _summary(
    submission_id: int,
    version: str,
    subset: str,
    values: dict[str, np.ndarray],
    validity: list[np.ndarray],
    interval: tuple[float, float],
    columns: tuple[str, ...],
) -> Summary:
    """Combine the seeds of one (version, subset), `values` as `_by_column` gives them and each seed's token
    `validity`: means, per-seed score spread, and `interval`, the CI of the seed-averaged token scores.

    A column's mean skips undefined values (NaN) as `summarize` does; the score is defined on every token.
    """
    tokens = len(validity[0])
    seed_scores = values["score"].mean(axis=1) if values["score"].size else np.full(len(validity), np.nan)
    failed_anywhere = np.zeros(tokens, dtype=bool)
    for valid in validity:
        failed_anywhere |= ~valid
    return seed_summary(
        submission_id,
        version,
        subset,
        seed_scores,
        interval,
        tokens=tokens,
        failed=int(np.count_nonzero(failed_anywhere)),
        means={column: defined_mean(values[column]) for column in columns},
    )


def seed_summary(
    submission_id: int,
    version: str,
    subset: str,
    seed_scores: np.ndarray,
    interval: tuple[float, float],
    *,
    tokens: int,
    failed: int,
    means: Mapping[str, float],
    two_stage: dict[str, Any] | None = None,
) -> Summary:
    """Return the Summary of an entry's seeds: `seed_scores` (one score per seed) give the seed count and the
    spread (std and max), `interval` the bootstrap interval (over tokens, or a two-stage entry's groups),
    `means` each column's mean over seeds (undefined: null)."""
    low, high = interval
    return Summary(
        submission_id=submission_id,
        metric_version=version,
        subset=subset,
        seeds=len(seed_scores),
        score_std=float(np.std(seed_scores)),
        score_max=float(np.max(seed_scores)),
        ci_low=low,
        ci_high=high,
        tokens=tokens,
        failed=failed,
        two_stage=two_stage,
        **{column: stored_value(mean) for column, mean in means.items()},
    )
