"""Admin actions, each written to the audit log: moderation, re-runs, rescore-all with its rank report, export."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from typing import Any

from sqlalchemy import or_, select
from sqlalchemy.orm import Session

from server.models import ApiToken, AuditEntry, Phase, Rescore, Status, Submission, Summary, Team
from server.services.errors import Conflict, NotFound
from server.services.leaderboard import leaderboard, phase_summaries, rank_change_report, subscore_columns
from server.services.scoring import cancel, reset_for_rerun
from server.services.submissions import get_submission


def actor_name(token: ApiToken | None) -> str:
    """Return how an actor appears in the audit log."""
    if token is None:
        return "command line"
    return f"admin token {token.prefix}…" + (f" ({token.name})" if token.name else "")


def audit(
    session: Session, actor: ApiToken | None, action: str, target_type: str, target_id: object, **details: Any
) -> AuditEntry:
    """Record an admin action."""
    entry = AuditEntry(
        actor=actor_name(actor),
        token_id=actor.id if actor is not None else None,
        action=action,
        target_type=target_type,
        target_id=str(target_id),
        details=details,
    )
    session.add(entry)
    session.flush()
    return entry


def audit_log(session: Session, limit: int = 200, offset: int = 0) -> Sequence[AuditEntry]:
    """Return audit entries, newest first."""
    return session.scalars(
        select(AuditEntry).order_by(AuditEntry.id.desc()).limit(limit).offset(offset)
    ).all()


def rerun_submission(session: Session, actor: ApiToken | None, submission_id: int) -> Submission:
    """Queue a new run of a submission that is not running (the caller enqueues it after commit)."""
    submission = get_submission(session, submission_id)
    if submission.status in (Status.queued, Status.running):
        raise Conflict(f"submission {submission_id} is already {submission.status}")
    previous = submission.status
    reset_for_rerun(session, submission)
    audit(session, actor, "rerun", "submission", submission_id, previous_status=previous, run=submission.run)
    return submission


def cancel_submission(session: Session, actor: ApiToken | None, submission_id: int) -> Submission:
    """Cancel a queued or running submission and refund it."""
    submission = get_submission(session, submission_id)
    previous = submission.status
    cancel(session, submission)
    audit(session, actor, "cancel", "submission", submission_id, previous_status=previous)
    return submission


def hide_submission(session: Session, actor: ApiToken | None, submission_id: int, hidden: bool) -> Submission:
    """Hide a submission from the leaderboard (or show it again); the team cannot undo it."""
    submission = get_submission(session, submission_id)
    submission.admin_hidden = hidden
    audit(session, actor, "hide" if hidden else "unhide", "submission", submission_id)
    return submission


def disqualify_submission(
    session: Session, actor: ApiToken | None, submission_id: int, disqualified: bool, reason: str
) -> Submission:
    """Disqualify a submission (or lift it) with a reason kept on the row and in the log."""
    submission = get_submission(session, submission_id)
    submission.disqualified = disqualified
    submission.disqualified_reason = reason if disqualified else ""
    audit(
        session,
        actor,
        "disqualify" if disqualified else "requalify",
        "submission",
        submission_id,
        reason=reason,
    )
    return submission


def start_rescore(
    session: Session, actor: ApiToken | None, phase: Phase, version: str, subset: str
) -> tuple[Rescore, list[Submission]]:
    """Snapshot the leaderboard and queue a new run of every scored entry of the phase (baselines included)."""
    before = leaderboard(session, phase, version, subset)
    submissions = session.scalars(
        select(Submission)
        .where(
            Submission.split_id == phase.split_id,
            or_(Submission.phase_id == phase.id, Submission.is_baseline.is_(True)),
            Submission.status == Status.scored,
        )
        .order_by(Submission.id)
    ).all()
    for submission in submissions:
        reset_for_rerun(session, submission)
    rescore = Rescore(
        metric_version=version,
        subset=subset,
        phase_id=phase.id,
        before=before,
        submission_ids=[submission.id for submission in submissions],
    )
    session.add(rescore)
    session.flush()
    audit(
        session,
        actor,
        "rescore_all",
        "phase",
        phase.name,
        version=version,
        subset=subset,
        rescore_id=rescore.id,
        submissions=len(submissions),
    )
    return rescore, list(submissions)


def rescore_report(session: Session, rescore_id: int) -> dict[str, Any]:
    """Return the rank changes of a rescore so far: complete once none of its submissions is queued or running."""
    rescore = session.get(Rescore, rescore_id)
    if rescore is None:
        raise NotFound(f"rescore {rescore_id} does not exist")
    phase = session.get(Phase, rescore.phase_id)
    assert phase is not None
    statuses = session.scalars(
        select(Submission.status).where(Submission.id.in_(rescore.submission_ids))
    ).all()
    pending = sum(status in (Status.queued, Status.running) for status in statuses)
    report = rank_change_report(
        rescore.before, leaderboard(session, phase, rescore.metric_version, rescore.subset)
    )
    return {
        "id": rescore.id,
        "version": rescore.metric_version,
        "subset": rescore.subset,
        "phase": phase.name,
        "created_at": rescore.created_at.isoformat(),
        "submissions": len(rescore.submission_ids),
        "pending": pending,
        "failed": sum(status == Status.failed for status in statuses),
        "complete": pending == 0,
        **report,
    }


def export_rows(session: Session, phase: Phase, version: str, subset: str) -> list[dict[str, Any]]:
    """Return every submission of the phase with a summary for (version, subset), moderation flags included."""
    columns = subscore_columns(version)
    query = (
        select(Summary, Submission, Team.name)
        .join(Submission, Summary.submission_id == Submission.id)
        .join(Team, Team.id == Submission.team_id)
        .where(*phase_summaries(phase, version, subset))
        .order_by(Submission.id)
    )
    return [
        {
            "submission_id": submission.id,
            "team": team,
            "method": submission.method,
            "baseline": submission.is_baseline,
            "status": submission.status,
            "score": summary.score,
            **{column: getattr(summary, column) for column in columns},
            "seeds": summary.seeds,
            "score_std": summary.score_std,
            "score_max": summary.score_max,
            "ci95_low": summary.ci_low,
            "ci95_high": summary.ci_high,
            "tokens": summary.tokens,
            "failed_tokens": summary.failed,
            "hidden": submission.hidden,
            "admin_hidden": submission.admin_hidden,
            "disqualified": submission.disqualified,
            "disqualified_reason": submission.disqualified_reason,
            "selected": submission.selected,
            "sha256": submission.sha256,
            "authors": submission.authors,
            "institution": submission.institution,
            "country": submission.country,
            "tech_report_url": submission.tech_report_url,
            "code_url": submission.code_url,
            "submitted_at": submission.created_at.isoformat(),
        }
        for summary, submission, team in session.execute(query).all()
    ]


def rows_to_csv(rows: list[dict[str, Any]]) -> str:
    """Return rows as CSV text with a header (empty string for no rows)."""
    if not rows:
        return ""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()
