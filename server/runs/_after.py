"""After a run is scored and committed: the integrity check of its split (server.services.integrity), done by a
task of its own so that the run neither waits on it nor fails with it, and that scoring does not wait on it: a
check that reaches a worker while chunks wait goes once to the back of the queue, behind them (the broker's
queue is first in, first out). Once only: it never waits longer than the chunks queued at that moment, and two
checks can never keep sending each other back."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.db import transaction
from server.models import ChunkState, ScoringChunk
from server.settings import Settings


def check_integrity_after_run(
    session_factory: sessionmaker[Session], settings: Settings, submission_id: int
) -> int | None:
    """Check the split of a scored submission, unless a check that read it already finished; return the
    check's id (its outcome, flags or error, is in the admin console), or None when none was needed."""
    # Here, not at the top: the integrity service reaches the admin service, which reaches server.runs.
    from server.services.integrity import run_check, start_check_after_run

    with transaction(session_factory) as session:
        check = start_check_after_run(session, submission_id)
        check_id = None if check is None else check.id
    if check_id is not None:
        run_check(session_factory, settings, check_id)
    return check_id


def chunks_waiting(session: Session) -> bool:
    """Whether a chunk of some run waits for a worker (queued in SQL: sent, or about to be sent again)."""
    waiting = select(ScoringChunk.id).where(ScoringChunk.state == ChunkState.queued).limit(1)
    return session.scalars(waiting).first() is not None
