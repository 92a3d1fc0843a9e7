"""Quotas per team and phase (per UTC day, total, in flight), checked under the team's submission lock.

The lock is a conditional-free UPDATE of the team row: on PostgreSQL it takes a row lock held until
commit, on SQLite the database write lock, so two uploads of one team are counted one after the other
and cannot both take the last slot. Counts come from the submission rows themselves (the truth),
so refunds are just `charged = false`.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, time, timedelta

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from server.models import ACTIVE_STATUSES, Phase, Submission, Team, TeamQuota, utc_now
from server.numbers import counted
from server.services.errors import QuotaExceeded


@dataclass(frozen=True)
class QuotaUsage:
    """One quota of a team in a phase: limit (None: unlimited), used, and when it resets (None: never by time)."""

    name: str
    limit: int | None
    used: int
    resets_at: datetime | None

    @property
    def exhausted(self) -> bool:
        return self.limit is not None and self.used >= self.limit


def next_utc_midnight(now: datetime) -> datetime:
    """Return the start of the UTC day after `now`."""
    return datetime.combine(now.date(), time(), tzinfo=now.tzinfo) + timedelta(days=1)


def lock_team(session: Session, team_id: int, now: datetime) -> None:
    """Serialise the submissions of a team until the transaction ends."""
    session.execute(update(Team).where(Team.id == team_id).values(last_submission_at=now))


def quota_usage(
    session: Session, team_id: int, phase: Phase, now: datetime | None = None
) -> list[QuotaUsage]:
    """Return the total, per-day and in-flight usage of a team in a phase, with the effective limits."""
    now = now or utc_now()
    override = session.scalar(
        select(TeamQuota).where(TeamQuota.team_id == team_id, TeamQuota.phase_id == phase.id)
    )

    def limit(name: str) -> int | None:
        value = getattr(override, name, None) if override is not None else None
        return value if value is not None else getattr(phase, name)

    mine = (Submission.team_id == team_id, Submission.phase_id == phase.id)
    charged = (*mine, Submission.charged.is_(True))
    day_start = next_utc_midnight(now) - timedelta(days=1)
    total = session.scalar(select(func.count()).where(*charged)) or 0
    today = session.scalar(select(func.count()).where(*charged, Submission.created_at >= day_start)) or 0
    in_flight = session.scalar(select(func.count()).where(*mine, Submission.status.in_(ACTIVE_STATUSES))) or 0
    return [
        QuotaUsage("total", limit("total"), total, None),
        QuotaUsage("per_day", limit("per_day"), today, next_utc_midnight(now)),
        QuotaUsage("in_flight", limit("in_flight"), in_flight, None),
    ]


def check_quota(session: Session, team_id: int, phase: Phase, now: datetime) -> None:
    """Raise QuotaExceeded for the first exhausted quota; call it after `lock_team` in the same transaction."""
    for usage in quota_usage(session, team_id, phase, now):
        if usage.exhausted:
            assert usage.limit is not None
            raise QuotaExceeded(usage.name, usage.limit, usage.used, usage.resets_at, _message(usage, phase))


def _message(usage: QuotaUsage, phase: Phase) -> str:
    what = {
        "total": f"{counted(usage.limit or 0, 'submission')} in phase {phase.name!r}",
        "per_day": f"{counted(usage.limit or 0, 'submission')} per UTC day in phase {phase.name!r}",
        "in_flight": f"{counted(usage.limit or 0, 'submission')} queued or running at once",
    }[usage.name]
    when = {
        "total": "it does not reset",
        "per_day": f"it resets at {usage.resets_at:%Y-%m-%d %H:%M} UTC" if usage.resets_at else "",
        "in_flight": "a slot frees when one of them finishes",
    }[usage.name]
    return f"quota exhausted: {what} ({usage.used} used); {when}"
