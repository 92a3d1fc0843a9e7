"""Finishing a run: after each chunk its progress; once every row is written, the aggregation, and scored.

The chunk that writes the last rows aggregates, in its own transaction. Rows are counted only once no chunk
of the run is queued or running: before that, one still has rows to write, and a navtest-size run holds
about 100,000 rows and 300 chunks, so a chunk reads the run's chunk records, never all of its rows.
"""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from scorer.versions import get_version
from server.models import FINISHED_CHUNK_STATES, LIVE_CHUNK_STATES, ScoringChunk, Status, utc_now
from server.runs._aggregate import aggregate_submission
from server.runs._run import expected_rows, is_current, locked_submission, rows_written, run_versions
from server.runs._two_stage import aggregate_two_stage_run
from server.services.errors import Conflict
from server.services.splits import subset_tokens


def live_chunks(session: Session, submission_id: int, run: int) -> int:
    """Return how many chunks of the run are queued or running."""
    query = select(func.count()).where(
        ScoringChunk.submission_id == submission_id,
        ScoringChunk.run == run,
        ScoringChunk.state.in_(LIVE_CHUNK_STATES),
    )
    return session.scalar(query) or 0


def finished_tokens(session: Session, submission_id: int, run: int) -> int:
    """Return how many tokens the finished chunks of the run hold: tokens with every row written, as the run's
    chunks never share a token (a chunk split up counts through its children)."""
    query = select(func.coalesce(func.sum(func.json_array_length(ScoringChunk.tokens)), 0)).where(
        ScoringChunk.submission_id == submission_id,
        ScoringChunk.run == run,
        ScoringChunk.state.in_(FINISHED_CHUNK_STATES),
    )
    return int(session.scalar(query) or 0)


def mark_scored(
    session: Session,
    submission_id: int,
    run: int,
    engine_version: str,
    bootstrap_samples: int,
    now: datetime | None = None,
) -> bool:
    """Aggregate a complete run into results and leaderboard summaries and mark it scored (False: not wanted)."""
    submission = locked_submission(session, submission_id)
    if not is_current(submission, run):
        return False
    done = rows_written(session, submission_id, run)
    if done != expected_rows(submission):
        raise Conflict(
            f"submission {submission_id} run {run}: {done} of {expected_rows(submission)} token rows written"
        )
    aggregate_submission(
        session, submission, subset_tokens(submission.split), engine_version, bootstrap_samples
    )
    for version in run_versions(submission.split):
        if get_version(version).two_stage:
            aggregate_two_stage_run(session, submission, version, engine_version, bootstrap_samples)
    session.flush()
    submission.status = Status.scored
    submission.progress = 100
    submission.finished_at = now or utc_now()
    session.flush()
    return True


def finish_if_complete(
    session: Session, submission_id: int, run: int, engine_version: str, bootstrap_samples: int
) -> bool:
    """Record the run's progress after a chunk; mark it scored when every row is written (True)."""
    submission = locked_submission(session, submission_id)
    if not is_current(submission, run):
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
