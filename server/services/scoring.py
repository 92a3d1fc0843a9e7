"""State transitions of a scoring run, called by the worker (and by admin actions): pure SQLAlchemy.

queued -> running -> scored | failed; any active state -> cancelled (admin). A re-run increments
`Submission.run`; every write names the run it belongs to, so a late chunk of an older run or of a
cancelled submission is dropped instead of mixing with the new one. Per-token rows are upserted on
(submission, metric version, seed, token): a redelivered chunk overwrites, it never duplicates.

A navtest-size run holds about 100,000 rows and 300 chunks: what a chunk does costs little beside its
scoring only if it reads its own tokens' rows and the run's chunk records, never all of the run's rows
(those are counted once, when no chunk of the run is left to write any).
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from scorer.versions import ALL_RESULT_COLUMNS, VERSIONS
from server.models import (
    ACTIVE_STATUSES,
    FailureKind,
    ScoringChunk,
    Status,
    Submission,
    TokenResultRow,
    utc_now,
)
from server.services.chunks import LIVE_STATES, finished_tokens, live_chunks
from server.services.errors import Conflict, NotFound
from server.services.leaderboard import aggregate_submission, stored_value
from server.services.splits import subset_tokens
from server.services.token_rows import upsert_token_rows

MAX_ERROR_CHARS = 2000
MAX_DETAIL_CHARS = 20000


@dataclass(frozen=True)
class ScoringJob:
    """Everything a worker needs to score one run of a submission but the file's bytes, stored under
    `stored_name`, and the split's tokens: both are large, and read only when the file is parsed."""

    submission_id: int
    run: int
    filename: str
    stored_name: str
    sha256: str  # of the upload: the stored bytes must still match it
    split_name: str
    split_dir: Path
    split_hash: str
    seed_count: int
    versions: tuple[str, ...]


# The versions every submission is scored under and the board shows: all the engine has.
BOARD_VERSIONS = tuple(VERSIONS)


def metric_versions() -> tuple[str, ...]:
    """Return the metric versions every submission is scored under."""
    return tuple(BOARD_VERSIONS)


def _locked(session: Session, submission_id: int) -> Submission:
    submission = session.scalar(select(Submission).where(Submission.id == submission_id).with_for_update())
    if submission is None:
        raise NotFound(f"submission {submission_id} does not exist")
    return submission


def _current(submission: Submission, run: int) -> bool:
    """Whether a write for `run` still belongs: the submission is active and not re-run since."""
    return submission.run == run and submission.status in ACTIVE_STATUSES


def load_job(session: Session, submission_id: int) -> ScoringJob:
    """Return the current run of a submission as a scoring job (its file named, not read)."""
    submission = session.get(Submission, submission_id)
    if submission is None:
        raise NotFound(f"submission {submission_id} does not exist")
    split = submission.split
    return ScoringJob(
        submission_id=submission.id,
        run=submission.run,
        filename=submission.filename,
        stored_name=submission.stored_name,
        sha256=submission.sha256,
        split_name=split.name,
        split_dir=Path(split.directory),
        split_hash=split.content_hash,
        seed_count=submission.seed_count,
        versions=metric_versions(),
    )


def claim_submission(
    session: Session, submission_id: int, worker: str, now: datetime | None = None
) -> int | None:
    """Mark an active submission running, claimed by `worker`; return its run, or None if it is done."""
    now = now or utc_now()
    submission = _locked(session, submission_id)
    if submission.status not in ACTIVE_STATUSES:
        return None
    submission.status = Status.running
    submission.worker = worker
    submission.attempts += 1
    submission.started_at = submission.started_at or now
    submission.claimed_at = now
    session.flush()
    return submission.run


def expected_rows(submission: Submission) -> int:
    """Return how many per-token rows a complete run holds: tokens x seeds x metric versions."""
    return submission.token_count * submission.seed_count * len(BOARD_VERSIONS)


def rows_written(session: Session, submission_id: int, run: int) -> int:
    """Return how many per-token rows of `run` are stored."""
    query = select(func.count()).where(
        TokenResultRow.submission_id == submission_id, TokenResultRow.run == run
    )
    return session.scalar(query) or 0


def completed_tokens(
    session: Session, submission_id: int, run: int, among: Collection[str] | None = None
) -> set[str] | None:
    """Return the tokens of `run` with every version and seed written, of `among` only if given (a chunk's
    tokens: an index finds their rows alone, whatever the size of the run); None when the run is no longer
    wanted.

    A redelivered or re-dispatched chunk scores only the tokens missing here.
    """
    submission = session.get(Submission, submission_id)
    if submission is None or not _current(submission, run):
        return None
    query = select(TokenResultRow.token).where(
        TokenResultRow.submission_id == submission_id, TokenResultRow.run == run
    )
    if among is not None:
        query = query.where(TokenResultRow.token.in_(among))
    grouped = query.group_by(TokenResultRow.token).having(
        func.count() == submission.seed_count * len(BOARD_VERSIONS)
    )
    return set(session.scalars(grouped).all())


def write_chunk_results(
    session: Session,
    submission_id: int,
    run: int,
    metric_version: str,
    results: Sequence[Any],
    worker: str,
    duration_s: float,
    now: datetime | None = None,
) -> bool:
    """Upsert one chunk of scorer TokenResults (seed None counts as 0); `finish_if_complete` then records
    the run's progress.

    Returns False, writing nothing, when the run is no longer wanted (cancelled, finished or re-run):
    the worker should then stop.
    """
    now = now or utc_now()
    submission = _locked(session, submission_id)
    if not _current(submission, run):
        return False
    if results:
        share = duration_s / len(results)
        upsert_token_rows(
            session,
            [
                (
                    *(submission_id, metric_version, result.seed or 0, result.token),
                    *(result.valid, result.error, run, worker, share, now, result.detail or None),
                    *(
                        stored_value(result.metrics.get(column)) if result.valid else None
                        for column in ALL_RESULT_COLUMNS
                    ),
                )
                for result in results
            ],
        )
    return True


def mark_scored(
    session: Session,
    submission_id: int,
    run: int,
    engine_version: str,
    bootstrap_samples: int,
    now: datetime | None = None,
) -> bool:
    """Aggregate a complete run into results and leaderboard summaries and mark it scored (False: not wanted)."""
    submission = _locked(session, submission_id)
    if not _current(submission, run):
        return False
    done = rows_written(session, submission_id, run)
    if done != expected_rows(submission):
        raise Conflict(
            f"submission {submission_id} run {run}: {done} of {expected_rows(submission)} token rows written"
        )
    aggregate_submission(
        session, submission, subset_tokens(submission.split), engine_version, bootstrap_samples
    )
    submission.status = Status.scored
    submission.progress = 100
    submission.finished_at = now or utc_now()
    session.flush()
    return True


def finish_if_complete(
    session: Session, submission_id: int, run: int, engine_version: str, bootstrap_samples: int
) -> bool:
    """Record the run's progress after a chunk; mark it scored when every row is written (the chunk that
    writes the last rows aggregates).

    Rows are counted only once no chunk of the run is queued or running: before that, one still has rows
    to write. Under the submission's row lock, the last chunk to finish sees every other one finished.
    """
    submission = _locked(session, submission_id)
    if not _current(submission, run):
        return False
    # 100 only once the results are aggregated.
    submission.progress = min(
        99, 100 * finished_tokens(session, submission_id, run) // max(submission.token_count, 1)
    )
    if live_chunks(session, submission_id, run):
        return False
    if rows_written(session, submission_id, run) != expected_rows(submission):
        return False  # tokens without a chunk: the reaper finds the run stalled and plans them again
    return mark_scored(session, submission_id, run, engine_version, bootstrap_samples)


def mark_failed(
    session: Session,
    submission_id: int,
    run: int,
    kind: FailureKind,
    error: str,
    detail: str | None = None,
    now: datetime | None = None,
) -> bool:
    """Mark a run failed with a team-visible `error` (admins also see `detail`); infrastructure failures are refunded."""
    submission = _locked(session, submission_id)
    if not _current(submission, run):
        return False
    submission.status = Status.failed
    submission.failure_kind = kind
    refund = kind == FailureKind.infrastructure
    suffix = " The submission was refunded; you can upload it again." if refund else ""
    submission.error = (error[:MAX_ERROR_CHARS] + suffix).strip()
    submission.error_detail = detail
    submission.charged = submission.charged and not refund
    submission.finished_at = now or utc_now()
    session.flush()
    return True


def stalled_runs(session: Session, claimed_before: datetime) -> list[int]:
    """Return the ids of running submissions claimed before `claimed_before` that have no live chunk.

    A worker plans a run's chunks right after claiming it, and the last chunk aggregates in its own
    transaction: a run left running with nothing queued or running was interrupted between claim and plan
    (or in a way nothing else repairs).
    """
    live = select(ScoringChunk.id).where(
        ScoringChunk.submission_id == Submission.id,
        ScoringChunk.run == Submission.run,
        ScoringChunk.state.in_(LIVE_STATES),
    )
    query = select(Submission.id).where(
        Submission.status == Status.running, Submission.claimed_at < claimed_before, ~live.exists()
    )
    return list(session.scalars(query.order_by(Submission.id)).all())


def requeue(session: Session, submission_id: int) -> bool:
    """Put a running submission back in the queue within its current run (the caller enqueues it again)."""
    submission = _locked(session, submission_id)
    if submission.status != Status.running:
        return False
    submission.status = Status.queued
    submission.queued_at = utc_now()
    session.flush()
    return True


def mark_requeued(session: Session, submission_ids: Sequence[int], now: datetime | None = None) -> None:
    """Record that queued submissions were sent again now (so they are not re-sent at every reaper pass)."""
    for submission_id in submission_ids:
        submission = _locked(session, submission_id)
        submission.queued_at = now or utc_now()
    session.flush()


def add_admin_detail(session: Session, submission_id: int, line: str) -> None:
    """Append a line to what admins see of a run's problems (the team sees per-token errors instead)."""
    submission = _locked(session, submission_id)
    submission.error_detail = "\n".join(filter(None, [submission.error_detail, line]))[-MAX_DETAIL_CHARS:]
    session.flush()


def stale_queued(session: Session, queued_before: datetime) -> list[int]:
    """Return the ids of submissions still queued since before `queued_before` (their task may be lost)."""
    query = select(Submission.id).where(
        Submission.status == Status.queued, Submission.queued_at < queued_before
    )
    return list(session.scalars(query.order_by(Submission.id)).all())


def reset_for_rerun(session: Session, submission: Submission) -> None:
    """Start a new run: queued, progress 0; earlier results stay on the leaderboard until the new run is scored."""
    submission.run += 1
    submission.status = Status.queued
    submission.queued_at = utc_now()
    submission.progress = 0
    submission.error = submission.error_detail = submission.failure_kind = None
    submission.finished_at = submission.claimed_at = None
    submission.worker = None
    session.flush()


def cancel(session: Session, submission: Submission, now: datetime | None = None) -> None:
    """Cancel an active submission; it no longer counts against the team's quotas."""
    if submission.status not in ACTIVE_STATUSES:
        raise Conflict(
            f"submission {submission.id} is {submission.status}: only queued or running ones can be cancelled"
        )
    submission.status = Status.cancelled
    submission.charged = False
    submission.finished_at = now or utc_now()
    session.flush()
