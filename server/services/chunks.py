"""Scoring chunks: the tokens of a run travel as tasks, and SQL records each so that nothing a broker loses is lost.

A chunk is `queued` when planned and sent, `running` while a worker process scores it (beating every
HEARTBEAT_SECONDS), then `done`. The reaper reads these rows, never the broker's internals:

- a running chunk whose beat stopped lost its process (killed, out of memory, machine gone, hard time
  limit): it is sent again with one more death on record;
- a queued chunk sent a while ago, when the broker's queue is idle, was lost by the broker (flushed,
  restarted without persistence, held by a dead worker until a visibility timeout): it is sent again.

A chunk that starts with a death on record is split, one token per chunk, so that a token that kills its
worker cannot take the others with it; a single token that POISON_DEATHS worker processes died with is not
scored again: its rows are written as failed, naming the cause, and the rest of the run goes on. A message may
arrive twice (Celery's redelivery after a lost worker, a re-send of a message that was only late): only a
queued chunk starts, so a duplicate drops, and only the reaper, which sees a beat stop, counts a death.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from enum import StrEnum
from typing import Any, cast

from sqlalchemy import CursorResult, Select, func, select, update
from sqlalchemy.orm import Session

from server.models import ChunkState, ScoringChunk, Status, Submission, utc_now
from server.services.splits import scene_starts
from server.services.workers import LIVE_WITHIN_S

POISON_DEATHS = 2
LIVE_STATES = (ChunkState.queued, ChunkState.running)
# Their rows are written: scored (done), or written as failed (a poisoned token).
FINISHED_STATES = (ChunkState.done, ChunkState.failed)


class StartAction(StrEnum):
    score = "score"  # the caller holds the chunk: score it, then finish it
    split_up = "split"  # re-planned one token per chunk: send `children`
    poisoned = "poisoned"  # its one token killed its workers: write it as failed, then finish it
    drop = "drop"  # done, held by another process, or no longer wanted


@dataclass(frozen=True)
class ChunkStart:
    action: StartAction
    tokens: tuple[str, ...] = ()
    children: tuple[int, ...] = ()
    context: tuple[str, ...] = ()  # scored beside the tokens for EC to pair with, not written


def _current_run(session: Session, submission_id: int, run: int) -> bool:
    submission = session.get(Submission, submission_id)
    return submission is not None and submission.run == run and submission.status == Status.running


def _with_contexts(
    submission: Submission, groups: list[list[str]], starts: Mapping[str, tuple[str, int]]
) -> list[ScoringChunk]:
    """Return queued chunks of the run for `groups` of tokens, each with the earlier frames it pairs with
    (`starts`: the split's `scene_starts`)."""
    from scorer.evaluate import pairing_contexts  # the engine is heavy: imported only where chunks are made

    contexts = pairing_contexts(starts, groups)
    return [
        ScoringChunk(submission_id=submission.id, run=submission.run, tokens=group, context=context)
        for group, context in zip(groups, contexts, strict=True)
    ]


def plan_chunks(
    session: Session, submission: Submission, tokens: Sequence[str], size: int, now: datetime | None = None
) -> list[int]:
    """Record queued chunks of `size` for those of `tokens` no live chunk of the run holds; return their ids.

    A chunk takes consecutive frames of a log (the split's tokens in log and time order) so that few of its
    tokens need a context to pair with.
    """
    held = {
        token
        for chunk_tokens in session.scalars(
            select(ScoringChunk.tokens).where(
                ScoringChunk.submission_id == submission.id,
                ScoringChunk.run == submission.run,
                ScoringChunk.state.in_(LIVE_STATES),
            )
        )
        for token in chunk_tokens
    }
    starts = scene_starts(session, submission.split)
    todo = sorted(
        (token for token in tokens if token not in held),
        key=lambda token: (starts.get(token, ("", 0)), token),
    )
    chunks = _with_contexts(
        submission, [todo[start : start + size] for start in range(0, len(todo), size)], starts
    )
    for chunk in chunks:
        chunk.sent_at = now or utc_now()
    session.add_all(chunks)
    session.flush()
    return [chunk.id for chunk in chunks]


def _split(session: Session, chunk: ScoringChunk, now: datetime) -> tuple[int, ...]:
    submission = session.get(Submission, chunk.submission_id)
    assert submission is not None  # start_chunk checked the run
    starts = scene_starts(session, submission.split)
    children = _with_contexts(submission, [[token] for token in chunk.tokens], starts)
    for child in children:
        child.deaths, child.sent_at = chunk.deaths, now
    session.add_all(children)
    chunk.state, chunk.finished_at = ChunkState.split_up, now
    session.flush()
    return tuple(child.id for child in children)


def start_chunk(
    session: Session, chunk_id: int, run: int, worker: str, now: datetime | None = None
) -> ChunkStart:
    """Take a queued chunk for `worker` (host/pid), or say why not: split, poisoned or dropped."""
    now = now or utc_now()
    chunk = session.scalar(select(ScoringChunk).where(ScoringChunk.id == chunk_id).with_for_update())
    if chunk is None or chunk.run != run or chunk.state != ChunkState.queued:
        return ChunkStart(StartAction.drop)
    if not _current_run(session, chunk.submission_id, run):
        return ChunkStart(StartAction.drop)
    tokens = tuple(chunk.tokens)
    if chunk.deaths and len(tokens) > 1:
        return ChunkStart(StartAction.split_up, tokens, _split(session, chunk, now))
    if chunk.deaths >= POISON_DEATHS:
        return ChunkStart(StartAction.poisoned, tokens)
    chunk.state, chunk.worker = ChunkState.running, worker
    chunk.starts += 1
    chunk.started_at = chunk.beat_at = now
    session.flush()
    return ChunkStart(StartAction.score, tokens, context=tuple(chunk.context))


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


def finish_chunk(
    session: Session, chunk_id: int, state: ChunkState = ChunkState.done, now: datetime | None = None
) -> None:
    """Mark a chunk done (its rows are written) or failed (its poisoned token is written as failed)."""
    session.execute(
        update(ScoringChunk)
        .where(ScoringChunk.id == chunk_id)
        .values(state=state, finished_at=now or utc_now())
    )


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


def live_chunks(session: Session, submission_id: int, run: int) -> int:
    """Return how many chunks of the run are queued or running."""
    query = select(func.count()).where(
        ScoringChunk.submission_id == submission_id,
        ScoringChunk.run == run,
        ScoringChunk.state.in_(LIVE_STATES),
    )
    return session.scalar(query) or 0


def finished_tokens(session: Session, submission_id: int, run: int) -> int:
    """Return how many tokens the finished chunks of the run hold: tokens with every row written, as the run's
    chunks never share a token (a chunk split up counts through its children)."""
    query = select(func.coalesce(func.sum(func.json_array_length(ScoringChunk.tokens)), 0)).where(
        ScoringChunk.submission_id == submission_id,
        ScoringChunk.run == run,
        ScoringChunk.state.in_(FINISHED_STATES),
    )
    return int(session.scalar(query) or 0)
