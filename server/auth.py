"""Bearer-token authentication: 401 when no usable token is given, 403 when the token's scope does not allow it."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta
from typing import Annotated

from fastapi import Depends, HTTPException, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from server.models import ApiToken, Approval, Scope, Team, utc_now
from server.rate_limits import FAILED_AUTHENTICATIONS, UPLOADS_PER_ADDRESS, UPLOADS_PER_TOKEN
from server.services.tokens import find_token, token_problem

LAST_USED_RESOLUTION = timedelta(minutes=1)  # avoid a write on every request


def get_session(request: Request) -> Iterator[Session]:
    """Yield a database session; anything not committed by the route is rolled back."""
    with request.app.state.session_factory() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session)]


def _unauthorized(message: str) -> HTTPException:
    return HTTPException(status_code=401, detail=message, headers={"WWW-Authenticate": "Bearer"})


def client_address(request: Request) -> str:
    """Return the address the request came from (as the proxy in front, if any, reports it to uvicorn)."""
    return request.client.host if request.client else "unknown"


# Declares the scheme in the OpenAPI schema (Swagger UI's "Authorize"); current_token reads the header itself
# so that a missing, malformed or unknown token each gets its own message.
BEARER = HTTPBearer(auto_error=False, description="an API token: `Authorization: Bearer <token>`")


def current_token(
    request: Request,
    session: SessionDep,
    _scheme: Annotated[HTTPAuthorizationCredentials | None, Security(BEARER)] = None,
) -> ApiToken:
    """Return the valid API token of the request (header `Authorization: Bearer <token>`).

    Wrong tokens are counted per client address: past FAILED_AUTHENTICATIONS, 429 until the window moves.
    A token is found by its sha256, never compared as text: the secret's bytes set no timing.
    """
    header = request.headers.get("Authorization", "")
    scheme, _, secret = header.partition(" ")
    if not header:
        raise _unauthorized("missing API token: send the header `Authorization: Bearer <token>`")
    limits, address = request.app.state.rate_limits, client_address(request)
    limits.check(FAILED_AUTHENTICATIONS, address)
    token: ApiToken | None = None
    if scheme.lower() != "bearer" or not secret.strip():
        problem: str | None = "malformed Authorization header: expected `Bearer <token>`"
    else:
        token = find_token(session, secret.strip())
        problem = token_problem(token)
    if problem is not None:
        limits.hit(FAILED_AUTHENTICATIONS, address)
        raise _unauthorized(problem)
    assert token is not None
    now = utc_now()
    if token.last_used_at is None or now - token.last_used_at > LAST_USED_RESOLUTION:
        token.last_used_at = now
        session.commit()
    return token


TokenDep = Annotated[ApiToken, Depends(current_token)]


def counted_upload(request: Request, token: TokenDep) -> None:
    """Count an upload against the token's and the client address's rate limits (429 past either)."""
    limits = request.app.state.rate_limits
    limits.hit(UPLOADS_PER_TOKEN, str(token.id))
    limits.hit(UPLOADS_PER_ADDRESS, client_address(request))


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


def approved_team_of(request: Request, session: Session) -> Team:
    """Return the approved team of the request's token: ApprovedTeamDep's checks, outside of a route
    (server.upload_gate runs them before an upload's body is read)."""
    return approved_team(current_team(team_token(current_token(request, session))))


TeamDep = Annotated[Team, Depends(current_team)]
ApprovedTeamDep = Annotated[Team, Depends(approved_team)]
AdminDep = Annotated[ApiToken, Depends(admin_token)]
