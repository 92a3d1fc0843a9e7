"""A run's state on its submission: queued -> running -> scored | failed; any active state -> cancelled (admin).

Claiming marks a run running for a worker; failing records a message the team may read (admins also see the
detail) and refunds what was not the team's fault; a re-run starts a new run, whose number every later write
names (server.runs._run).
"""

from __future__ import annotations

from datetime import datetime

from sqlalchemy.orm import Session

from server.models import ACTIVE_STATUSES, FailureKind, Status, Submission, utc_now
from server.runs._run import is_current, locked_submission
from server.services.errors import Conflict

MAX_ERROR_CHARS = 2000


def claim_submission(
    session: Session, submission_id: int, worker: str, now: datetime | None = None
) -> int | None:
    """Mark an active submission running, claimed by `worker`; return its run, or None if it is done."""
    now = now or utc_now()
    submission = locked_submission(session, submission_id)
    if submission.status not in ACTIVE_STATUSES:
        return None
    submission.status = Status.running
    submission.worker = worker
    submission.attempts += 1
    submission.started_at = submission.started_at or now
    submission.claimed_at = now
    session.flush()
    return submission.run


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
    submission = locked_submission(session, submission_id)
    if not is_current(submission, run):
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
