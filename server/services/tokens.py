"""API tokens: random secrets shown once, stored as sha256, with scope, expiry and revocation."""

from __future__ import annotations

import hashlib
import secrets
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.models import ApiToken, Scope, Team, utc_now
from server.services.errors import Conflict, NotFound

TOKEN_PREFIX = "nlb_"


def hash_token(secret: str) -> str:
    """Return the stored form of a token secret."""
    return hashlib.sha256(secret.encode()).hexdigest()


def create_token(
    session: Session, scope: Scope, team: Team | None, name: str = "", expires_at: datetime | None = None
) -> tuple[ApiToken, str]:
    """Create a token and return it with its secret, which is never stored and cannot be shown again."""
    if (scope == Scope.team) != (team is not None):
        raise Conflict("a team token needs a team and an admin token must not have one")
    if team is not None and team.is_system:
        raise Conflict(f"team {team.name!r} is a system team and cannot hold tokens")
    secret = TOKEN_PREFIX + secrets.token_urlsafe(32)
    token = ApiToken(
        scope=scope,
        team=team,
        name=name,
        token_hash=hash_token(secret),
        prefix=secret[:12],
        expires_at=expires_at,
    )
    session.add(token)
    session.flush()
    return token, secret


def find_token(session: Session, secret: str) -> ApiToken | None:
    """Return the token whose secret this is (valid or not), or None."""
    return session.scalar(select(ApiToken).where(ApiToken.token_hash == hash_token(secret)))


def token_problem(token: ApiToken | None, now: datetime | None = None) -> str | None:
    """Return why a token cannot authenticate (unknown, revoked, expired), or None when it can."""
    now = now or utc_now()
    if token is None:
        return "unknown API token"
    if token.revoked_at is not None:
        return f"API token {token.prefix}… was revoked at {token.revoked_at.isoformat()}"
    if token.expires_at is not None and token.expires_at <= now:
        return f"API token {token.prefix}… expired at {token.expires_at.isoformat()}"
    return None


def revoke_token(session: Session, token_id: int) -> ApiToken:
    """Revoke a token (idempotent: the first revocation time is kept)."""
    token = session.get(ApiToken, token_id)
    if token is None:
        raise NotFound(f"API token {token_id} does not exist")
    if token.revoked_at is None:
        token.revoked_at = utc_now()
    return token
