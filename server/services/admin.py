"""Admin actions, each written to the audit log: teams, tokens, quotas, splits and phases, moderation, re-runs,
rescore-all with its rank report, export. The API's admin routes and `navsim-lb admin` call these, so an action
is recorded the same way whoever took it (`actor` None: the command line on the server machine).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy import or_, select
from sqlalchemy.orm import Session

from scorer.versions import get_version
from server.models import (
    ApiToken,
    Approval,
    AuditEntry,
    Phase,
    Rescore,
    Scope,
    Split,
    Status,
    Submission,
    Summary,
    Team,
    TeamQuota,
)
from server.object_store import ObjectStore
from server.runs import cancel, reset_for_rerun
from server.services.errors import Conflict, NotFound
from server.services.leaderboard import (
    STAGES,
    leaderboard,
    phase_summaries,
    phase_version,
    rank_change_report,
    subscore_columns,
)
from server.services.splits import create_phase, register_split, split_by_name
from server.services.submissions import add_baselines, get_submission
from server.services.teams import create_team, set_approval, set_team_quota
from server.services.tokens import create_token, revoke_token


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


def add_team(
    session: Session,
    actor: ApiToken | None,
    name: str,
    members: list[str],
    affiliation: str,
    approval: Approval,
) -> Team:
    """Create a team (an organiser's: approved unless asked otherwise)."""
    team = create_team(session, name, members, affiliation, approval)
    audit(session, actor, "create_team", "team", team.id, name=team.name, approval=approval.value)
    return team


def decide_team(session: Session, actor: ApiToken | None, team_id: int, approval: Approval) -> Team:
    """Approve a team (its tokens may submit) or reject it (they may not)."""
    team = set_approval(session, team_id, approval)
    action = "approve_team" if approval == Approval.approved else "reject_team"
    audit(session, actor, action, "team", team_id, name=team.name)
    return team


def issue_token(
    session: Session, actor: ApiToken | None, team: Team | None, name: str, expires_at: datetime | None
) -> tuple[ApiToken, str]:
    """Issue a team token (`team`) or an admin token (None); return it with its secret, shown once."""
    scope = Scope.team if team is not None else Scope.admin
    token, secret = create_token(session, scope, team, name, expires_at)
    team_name = team.name if team is not None else None
    audit(
        session,
        actor,
        "create_token",
        "token",
        token.id,
        scope=scope.value,
        team=team_name,
        prefix=token.prefix,
    )
    return token, secret


def withdraw_token(session: Session, actor: ApiToken | None, token_id: int) -> ApiToken:
    """Revoke a token (team or admin)."""
    token = revoke_token(session, token_id)
    audit(session, actor, "revoke_token", "token", token_id, prefix=token.prefix)
    return token


def override_quotas(
    session: Session,
    actor: ApiToken | None,
    team_id: int,
    phase: Phase,
    per_day: int | None,
    total: int | None,
    in_flight: int | None,
) -> TeamQuota:
    """Override a team's quotas in a phase (None keeps the phase default for that quota)."""
    quota = set_team_quota(session, team_id, phase, per_day, total, in_flight)
    audit(
        session,
        actor,
        "set_quota",
        "team",
        team_id,
        phase=phase.name,
        per_day=per_day,
        total=total,
        in_flight=in_flight,
    )
    return quota


def add_split(
    session: Session,
    actor: ApiToken | None,
    name: str,
    directory: Path | str,
    public_tokens: list[str] | None,
    scenes_public: bool,
    baselines_to: ObjectStore | None,
) -> tuple[Split, list[Submission]]:
    """Register a split; with `baselines_to` (the submissions' store), create its two baseline submissions too.
    The caller enqueues the baselines after the commit."""
    split = register_split(session, name, directory, public_tokens, scenes_public)
    baselines = add_baselines(session, split, baselines_to) if baselines_to is not None else []
    audit(
        session,
        actor,
        "register_split",
        "split",
        split.name,
        directory=split.directory,
        content_hash=split.content_hash,
        tokens=split.token_count,
        public_tokens=None if public_tokens is None else len(public_tokens),
        scenes_public=split.scenes_public,
        baseline_submissions=[submission.id for submission in baselines],
    )
    return split, baselines


def add_phase(
    session: Session,
    actor: ApiToken | None,
    name: str,
    split_name: str,
    opens_at: datetime | None,
    closes_at: datetime | None,
    per_day: int | None,
    total: int | None,
    in_flight: int | None,
) -> Phase:
    """Create a phase on a registered split, with its default quotas (None: unlimited)."""
    split = split_by_name(session, split_name)
    phase = create_phase(session, name, split, opens_at, closes_at, per_day, total, in_flight)
    audit(
        session,
        actor,
        "create_phase",
        "phase",
        phase.name,
        split=split.name,
        opens_at=phase.opens_at.isoformat(),
        closes_at=None if phase.closes_at is None else phase.closes_at.isoformat(),
        per_day=per_day,
        total=total,
        in_flight=in_flight,
    )
    return phase


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
    session: Session,
    actor: ApiToken | None,
    phase: Phase,
    version: str,
    subset: str,
    compare_with: str | None = None,
) -> tuple[Rescore, list[Submission]]:
    """Snapshot the leaderboard under `compare_with` and queue a new run of every scored entry of the phase
    (baselines included). By default the snapshot is `version`'s, or the default version's when `version` ranks
    no entry yet: rescoring under a version new on the board then reports how it reorders the board."""
    before_version = phase_version(phase, compare_with or version)
    before = leaderboard(session, phase, before_version, subset)
    if compare_with is None and not any(not row["baseline"] for row in before):
        before_version = phase_version(phase, None)
        before = leaderboard(session, phase, before_version, subset)
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
        before_version=before_version,
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
        compared_with=before_version,
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
    before_version = rescore.before_version or rescore.metric_version
    return {
        "id": rescore.id,
        "version": rescore.metric_version,
        "before_version": before_version,
        "score_label": get_version(rescore.metric_version).score_label,
        "before_score_label": get_version(before_version).score_label,
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
            **{
                f"{stage}_score": summary.two_stage[stage]["score"]
                for stage in STAGES
                if summary.two_stage is not None
            },
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
