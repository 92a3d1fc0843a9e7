"""Planning a run: its tokens without rows become queued chunks, each with the earlier frames it pairs with.

A chunk takes consecutive frames of a log (the split's tokens in log and time order) so that few of its tokens
need a context to pair with (v2.2's two-frame comfort; scorer.evaluate.pairing_contexts). A chunk whose
process died is planned again one token per chunk (`split_chunk`), so that a token that kills its worker
cannot take the others with it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.models import LIVE_CHUNK_STATES, ChunkState, ScoringChunk, Submission, utc_now
from server.runs._finish import finish_if_complete
from server.runs._run import completed_tokens
from server.services.splits import scene_starts, split_tokens


@dataclass(frozen=True)
class Plan:
    """What planning a run did: chunks to send, or the run finished (every row was there), or dropped."""

    chunks: tuple[int, ...] = ()
    finished: bool = False
    dropped: bool = False


def plan_run(
    session: Session,
    submission_id: int,
    run: int,
    chunk_size: int,
    engine_version: str,
    bootstrap_samples: int,
) -> Plan:
    """Record the chunks of a claimed run's tokens without rows (the caller sends them), or finish the run
    when every row was written before an interruption."""
    submission = session.get(Submission, submission_id)
    done = completed_tokens(session, submission_id, run)
    if submission is None or done is None:
        return Plan(dropped=True)
    missing = [token for token in split_tokens(submission.split) if token not in done]
    if not missing:
        finish_if_complete(session, submission_id, run, engine_version, bootstrap_samples)
        return Plan(finished=True)
    # A chunk holds about chunk_size (token, seed) pairs, whatever the number of seeds.
    size = max(1, chunk_size // submission.seed_count)
    return Plan(chunks=tuple(plan_chunks(session, submission, missing, size)))


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
    """Record queued chunks of `size` for those of `tokens` no live chunk of the run holds; return their ids."""
    held = {
        token
        for chunk_tokens in session.scalars(
            select(ScoringChunk.tokens).where(
                ScoringChunk.submission_id == submission.id,
                ScoringChunk.run == submission.run,
                ScoringChunk.state.in_(LIVE_CHUNK_STATES),
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


def split_chunk(session: Session, chunk: ScoringChunk, now: datetime) -> tuple[int, ...]:
    """Plan a chunk's tokens again one per chunk, each inheriting its deaths; return the new chunks' ids."""
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
