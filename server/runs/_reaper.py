"""The reaper's decisions: what died or was lost is sent again, what cannot finish is failed (refunded).

It holds the broker to the SQL records, never to the broker's internals:

- a running chunk whose beat stopped lost its process (killed, out of memory, machine gone, hard time
  limit): it is sent again with one more death on record (server.runs._chunks splits it, then scores each
  token in a process of its own, which sees a death of the token's making); the run fails once the chunk ran
  past the hard limit, or when the chunk's workers were lost LOST_DEATHS times (the workers, not the token,
  keep dying: the team is refunded);
- when the broker's queue is idle, what waits in SQL was lost by the broker (flushed, restarted without
  persistence) or is held by a worker that took it a moment ago: a queued chunk sent more than one reaper
  interval ago is sent again (a duplicate drops), a running run with nothing queued or running is planned
  again (failed after `max_attempts` claims), and a submission still queued is sent again.

The caller sends what the returned `Reaped` names, after the transaction: a message sent before its record
is committed could start before the record says it may.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.models import LIVE_CHUNK_STATES, FailureKind, ScoringChunk, Status, Submission, utc_now
from server.runs._chunks import dead_chunks, forgotten_chunks, resend_chunk
from server.runs._run import locked_submission
from server.runs._state import mark_failed

LOST_DEATHS = 5


@dataclass
class Reaped:
    """What a reaper pass decided: chunks (submission, run, chunk) and submissions to send, runs failed."""

    chunks: list[tuple[int, int, int]] = field(default_factory=list)
    submissions: list[int] = field(default_factory=list)
    failed: list[int] = field(default_factory=list)


def reap_dead_chunks(session: Session, now: datetime, hard_limit_s: float) -> Reaped:
    """Send again the chunks whose process stopped beating; fail the run of one past the hard time limit, or
    of one whose workers were lost LOST_DEATHS times.

    A beat that stopped is proof on its own: the chunk is sent again whatever the queue holds.
    """
    reaped = Reaped()
    for chunk in dead_chunks(session, now):
        message = _run_failure(chunk, now, hard_limit_s)
        if message is None:
            chunk_id = resend_chunk(session, chunk, died=True, now=now)
            reaped.chunks.append((chunk.submission_id, chunk.run, chunk_id))
            continue
        detail = (
            f"chunk {chunk.id} of {len(chunk.tokens)} tokens, started {chunk.started_at} by {chunk.worker}"
        )
        mark_failed(session, chunk.submission_id, chunk.run, FailureKind.infrastructure, message, detail)
        reaped.failed.append(chunk.submission_id)
    return reaped


def _run_failure(chunk: ScoringChunk, now: datetime, hard_limit_s: float) -> str | None:
    """Return why the run of a chunk whose process died cannot go on (the team's message), or None."""
    assert chunk.started_at is not None
    if (now - chunk.started_at).total_seconds() >= hard_limit_s:
        return f"scoring was stopped at the hard time limit of {hard_limit_s:.0f} s"
    if chunk.deaths + 1 >= LOST_DEATHS:
        return f"the workers scoring a part of this submission were lost {chunk.deaths + 1} times"
    return None


def reap_lost_work(session: Session, now: datetime, sent_before: datetime, max_attempts: int) -> Reaped:
    """Send again what was sent before `sent_before` and waits in SQL; call it only when the queue is idle."""
    reaped = Reaped()
    for chunk in forgotten_chunks(session, sent_before):
        chunk_id = resend_chunk(session, chunk, died=False, now=now)
        reaped.chunks.append((chunk.submission_id, chunk.run, chunk_id))
    for submission_id in stalled_runs(session, sent_before):
        submission = session.get(Submission, submission_id)
        assert submission is not None  # a stalled run's submission
        if submission.attempts >= max_attempts:
            message = f"scoring was interrupted {submission.attempts} times (a worker was lost or too slow)"
            detail = f"claimed at {submission.claimed_at}; last worker {submission.worker}"
            mark_failed(session, submission_id, submission.run, FailureKind.infrastructure, message, detail)
            reaped.failed.append(submission_id)
        elif requeue(session, submission_id):
            reaped.submissions.append(submission_id)
    resent = stale_queued(session, sent_before)
    mark_requeued(session, resent, now)
    reaped.submissions += resent
    return reaped


def stalled_runs(session: Session, claimed_before: datetime) -> list[int]:
    """Return the ids of running submissions claimed before `claimed_before` that have no live chunk.

    A worker plans a run's chunks right after claiming it, and the last chunk aggregates in its own
    transaction: a run left running with nothing queued or running was interrupted between claim and plan
    (or in a way nothing else repairs).
    """
    live = select(ScoringChunk.id).where(
        ScoringChunk.submission_id == Submission.id,
        ScoringChunk.run == Submission.run,
        ScoringChunk.state.in_(LIVE_CHUNK_STATES),
    )
    query = select(Submission.id).where(
        Submission.status == Status.running, Submission.claimed_at < claimed_before, ~live.exists()
    )
    return list(session.scalars(query.order_by(Submission.id)).all())


def requeue(session: Session, submission_id: int) -> bool:
    """Put a running submission back in the queue within its current run (the caller enqueues it again)."""
    submission = locked_submission(session, submission_id)
    if submission.status != Status.running:
        return False
    submission.status = Status.queued
    submission.queued_at = utc_now()
    session.flush()
    return True


def stale_queued(session: Session, queued_before: datetime) -> list[int]:
    """Return the ids of submissions still queued since before `queued_before` (their task may be lost)."""
    query = select(Submission.id).where(
        Submission.status == Status.queued, Submission.queued_at < queued_before
    )
    return list(session.scalars(query.order_by(Submission.id)).all())


def mark_requeued(session: Session, submission_ids: list[int], now: datetime) -> None:
    """Record that queued submissions were sent again now (so they are not re-sent at every reaper pass)."""
    for submission_id in submission_ids:
        locked_submission(session, submission_id).queued_at = now
    session.flush()
