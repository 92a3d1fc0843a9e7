"""Teams: creation, approval and per-phase quota overrides."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.models import Approval, Phase, Team, TeamQuota
from server.services.errors import Conflict, NotFound

BASELINE_TEAM = "NAVSIM baselines"


def create_team(
    session: Session,
    name: str,
    members: list[str] | None = None,
    affiliation: str = "",
    approval: Approval = Approval.pending,
) -> Team:
    """Create a team; names are unique."""
    name = name.strip()
    if not name:
        raise Conflict("a team needs a name")
    if session.scalar(select(Team.id).where(Team.name == name)) is not None:
        raise Conflict(f"team {name!r} already exists")
    team = Team(name=name, members=list(members or []), affiliation=affiliation, approval=approval)
    session.add(team)
    session.flush()
    return team


def list_teams(session: Session) -> list[Team]:
    """Return every team but the system's, pending ones first, then by id."""
    teams = session.scalars(select(Team).where(Team.is_system.is_(False)).order_by(Team.id)).all()
    return sorted(teams, key=lambda team: team.approval != Approval.pending)


def get_team(session: Session, team_id: int) -> Team:
    """Return the team or raise NotFound."""
    team = session.get(Team, team_id)
    if team is None:
        raise NotFound(f"team {team_id} does not exist")
    return team


def team_by_name(session: Session, name: str) -> Team:
    """Return the team called `name` or raise NotFound."""
    team = session.scalar(select(Team).where(Team.name == name))
    if team is None:
        raise NotFound(f"team {name!r} does not exist")
    return team


def set_approval(session: Session, team_id: int, approval: Approval) -> Team:
    """Approve or reject a team."""
    team = get_team(session, team_id)
    team.approval = approval
    return team


def baseline_team(session: Session) -> Team:
    """Return the system team owning baseline submissions, creating it on first use."""
    team = session.scalar(select(Team).where(Team.is_system.is_(True), Team.name == BASELINE_TEAM))
    if team is None:
        team = Team(
            name=BASELINE_TEAM, members=[], affiliation="", approval=Approval.approved, is_system=True
        )
        session.add(team)
        session.flush()
    return team


def set_team_quota(
    session: Session,
    team_id: int,
    phase: Phase,
    per_day: int | None,
    total: int | None,
    in_flight: int | None,
) -> TeamQuota:
    """Override a team's quotas in a phase (None keeps the phase default for that quota)."""
    get_team(session, team_id)
    quota = session.scalar(
        select(TeamQuota).where(TeamQuota.team_id == team_id, TeamQuota.phase_id == phase.id)
    )
    if quota is None:
        quota = TeamQuota(team_id=team_id, phase_id=phase.id)
        session.add(quota)
    quota.per_day, quota.total, quota.in_flight = per_day, total, in_flight
    session.flush()
    return quota
