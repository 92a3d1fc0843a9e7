"""Bearer-token authentication: 401 when no usable token is given, 403 when the token's scope does not allow it."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from sqlalchemy.orm import Session

from server.models import ApiToken, Approval, Scope, Team, utc_now
from server.services.tokens import find_token, token_problem

LAST_USED_RESOLUTION = timedelta(minutes=1)  # avoid a write on every request


def get_session(request: Request) -> Iterator[Session]:
    """Yield a database session; anything not committed by the route is rolled back."""
    with request.app.state.session_factory() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session)]


def _unauthorized(message: str) -> HTTPException:
    return HTTPException(status_code=401, detail=message, headers={"WWW-Authenticate": "Bearer"})


def current_token(request: Request, session: SessionDep) -> ApiToken:
    """Return the valid API token of the request (header `Authorization: Bearer <token>`)."""
    header = request.headers.get("Authorization", "")
    scheme, _, secret = header.partition(" ")
    if not header:
        raise _unauthorized("missing API token: send the header `Authorization: Bearer <token>`")
    if scheme.lower() != "bearer" or not secret.strip():
        raise _unauthorized("malformed Authorization header: expected `Bearer <token>`")
    token = find_token(session, secret.strip())
    problem = token_problem(token)
    if problem is not None:
        raise _unauthorized(problem)
    assert token is not None
    now = utc_now()
    if token.last_used_at is None or now - token.last_used_at > LAST_USED_RESOLUTION:
        token.last_used_at = now
        session.commit()
    return token


TokenDep = Annotated[ApiToken, Depends(current_token)]


def team_token(token: TokenDep) -> ApiToken:
    """Return the token if it is a team token."""
    if token.scope != Scope.team:
        raise HTTPException(status_code=403, detail="this route needs a team token")
    return token


def current_team(token: Annotated[ApiToken, Depends(team_token)]) -> Team:
    """Return the team of a team token."""
    assert token.team is not None
    return token.team


def approved_team(team: Annotated[Team, Depends(current_team)]) -> Team:
    """Return the team if an admin approved it."""
    if team.approval != Approval.approved:
        raise HTTPException(
            status_code=403, detail=f"team {team.name!r} is {team.approval}: an admin must approve it first"
        )
    return team


def admin_token(token: TokenDep) -> ApiToken:
    """Return the token if it is an admin token."""
    if token.scope != Scope.admin:
        raise HTTPException(status_code=403, detail="this route needs an admin token")
    return token


TeamDep = Annotated[Team, Depends(current_team)]
ApprovedTeamDep = Annotated[Team, Depends(approved_team)]
AdminDep = Annotated[ApiToken, Depends(admin_token)]
