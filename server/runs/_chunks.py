"""Scoring chunks: the tokens of a run travel as tasks, and SQL records each so that nothing a broker loses is lost.

A chunk is `queued` when planned and sent, `running` while a worker process scores it (beating every
HEARTBEAT_SECONDS), then `done`. The reaper reads these rows, never the broker's internals:

- a running chunk whose beat stopped lost its process (killed, out of memory, machine gone, hard time
  limit): it is sent again with one more death on record;
- a queued chunk sent a while ago, when the broker's queue is idle, was lost by the broker (flushed,
  restarted without persistence, held by a dead worker until a visibility timeout): it is sent again.

A chunk that starts with a death on record is split, one token per chunk, so that a token that kills its
worker cannot take the others with it; a single token with a death on record is scored `isolated`, in a
process of its own (worker.isolated). If that process dies, the death is the token's: its rows are written as
failed, naming the cause, and the rest of the run goes on. If the worker holding it is lost instead (killed
from outside, its machine gone), nothing is known of the token: it is one more death, and the chunk goes out
again (server.runs._reaper fails the run after LOST_DEATHS of them). A message may arrive twice (Celery's
redelivery after a lost worker, a re-send of a message that was only late): only a queued chunk starts, so a
duplicate drops, and only the reaper, which sees a beat stop, counts a worker's death.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta
from enum import StrEnum
from typing import Any, cast

from sqlalchemy import CursorResult, Select, select, update
from sqlalchemy.orm import Session

from server.models import ChunkState, ScoringChunk, Status, Submission, utc_now
from server.runs._plan import split_chunk
from server.services.workers import LIVE_WITHIN_S


class StartAction(StrEnum):
    score = "score"  # the caller holds the chunk: score it, then write it
    split_up = "split"  # re-planned one token per chunk: send `children`
    drop = "drop"  # done, held by another process, or no longer wanted


@dataclass(frozen=True)
class ChunkStart:
    chunk_id: int
    action: StartAction
    tokens: tuple[str, ...] = ()
    children: tuple[int, ...] = ()
    context: tuple[str, ...] = ()  # scored beside the tokens for EC to pair with, not written
    isolated: bool = False  # one token with a death on record: scored in a process of its own


def _current_run(session: Session, submission_id: int, run: int) -> bool:
    submission = session.get(Submission, submission_id)
    return submission is not None and submission.run == run and submission.status == Status.running


def start_chunk(
    session: Session, chunk_id: int, run: int, worker: str, now: datetime | None = None
) -> ChunkStart:
    """Take a queued chunk for `worker` (host/pid), or say why not: split or dropped."""
    now = now or utc_now()
    chunk = session.scalar(select(ScoringChunk).where(ScoringChunk.id == chunk_id).with_for_update())
    if chunk is None or chunk.run != run or chunk.state != ChunkState.queued:
        return ChunkStart(chunk_id, StartAction.drop)
    if not _current_run(session, chunk.submission_id, run):
        return ChunkStart(chunk_id, StartAction.drop)
    tokens = tuple(chunk.tokens)
    if chunk.deaths and len(tokens) > 1:
        return ChunkStart(chunk_id, StartAction.split_up, tokens, split_chunk(session, chunk, now))
    chunk.state, chunk.worker = ChunkState.running, worker
    chunk.starts += 1
    chunk.started_at = chunk.beat_at = now
    session.flush()
    context = tuple(chunk.context)
    return ChunkStart(chunk_id, StartAction.score, tokens, context=context, isolated=bool(chunk.deaths))


def beat_chunk(session: Session, chunk_id: int, worker: str, now: datetime | None = None) -> bool:
    """Record that `worker` still scores the chunk; False when the chunk is no longer its own."""
    statement = (
        update(ScoringChunk)
        .where(
            ScoringChunk.id == chunk_id,
            ScoringChunk.state == ChunkState.running,
            ScoringChunk.worker == worker,
        )
        .values(beat_at=now or utc_now())
    )
    return bool(cast(CursorResult[Any], session.execute(statement)).rowcount)


def _of_running_runs(state: ChunkState) -> Select[ScoringChunk]:
    return (
        select(ScoringChunk)
        .join(Submission, Submission.id == ScoringChunk.submission_id)
        .where(
            ScoringChunk.state == state,
            Submission.status == Status.running,
            Submission.run == ScoringChunk.run,
        )
        .order_by(ScoringChunk.id)
    )


def dead_chunks(session: Session, now: datetime | None = None) -> list[ScoringChunk]:
    """Return the running chunks of running runs whose process stopped beating."""
    stopped_before = (now or utc_now()) - timedelta(seconds=LIVE_WITHIN_S)
    query = _of_running_runs(ChunkState.running).where(ScoringChunk.beat_at < stopped_before)
    return list(session.scalars(query.with_for_update(of=ScoringChunk)).all())


def forgotten_chunks(session: Session, sent_before: datetime) -> list[ScoringChunk]:
    """Return the queued chunks of running runs sent before `sent_before` (lost, if the queue is idle)."""
    query = _of_running_runs(ChunkState.queued).where(ScoringChunk.sent_at < sent_before)
    return list(session.scalars(query.with_for_update(of=ScoringChunk)).all())


def resend_chunk(session: Session, chunk: ScoringChunk, died: bool, now: datetime | None = None) -> int:
    """Put a chunk back in the queue (one more death if its process died); return its id, to send."""
    chunk.state, chunk.worker = ChunkState.queued, None
    chunk.deaths += int(died)
    chunk.sent_at = now or utc_now()
    session.flush()
    return chunk.id
