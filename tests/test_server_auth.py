"""Authentication and scopes: missing, malformed, unknown, revoked or expired tokens are 401; a token of the
wrong scope, or of a team not approved yet, is 403. Only the hash of a token is stored."""

from __future__ import annotations

from datetime import timedelta

from server_testing import World, add_team, team_row
from sqlalchemy import select

from server.db import transaction
from server.models import ApiToken, Approval, Scope, utc_now
from server.services.tokens import create_token, hash_token, revoke_token


def _bearer(secret: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {secret}"}


def test_missing_malformed_and_unknown_tokens_are_401(world: World) -> None:
    for headers in (
        {},
        {"Authorization": "Basic abc"},
        {"Authorization": "Bearer"},
        _bearer("nlb_not-a-token"),
    ):
        response = world.client.get("/api/v1/submissions", headers=headers)
        assert response.status_code == 401, headers
        assert response.headers["WWW-Authenticate"] == "Bearer"
    assert "missing API token" in world.client.get("/api/v1/submissions").json()["detail"]
    assert world.client.get("/api/v1/submissions", headers=world.team_headers()).status_code == 200


def test_revoked_and_expired_tokens_are_401(world: World) -> None:
    with transaction(world.factory) as session:
        team = team_row(session, world.team_id)
        revoked, revoked_secret = create_token(session, Scope.team, team, "old")
        _, expired_secret = create_token(session, Scope.team, team, "short", utc_now() - timedelta(seconds=1))
        _, valid_secret = create_token(session, Scope.team, team, "long", utc_now() + timedelta(days=1))
        revoke_token(session, revoked.id)
    revoked_answer = world.client.get("/api/v1/submissions", headers=_bearer(revoked_secret))
    expired_answer = world.client.get("/api/v1/submissions", headers=_bearer(expired_secret))
    assert (revoked_answer.status_code, expired_answer.status_code) == (401, 401)
    assert "revoked" in revoked_answer.json()["detail"] and "expired" in expired_answer.json()["detail"]
    assert world.client.get("/api/v1/submissions", headers=_bearer(valid_secret)).status_code == 200


def test_revocation_through_the_admin_api(world: World) -> None:
    with world.session() as session:
        token_id = session.scalar(select(ApiToken.id).where(ApiToken.team_id == world.team_id))
    assert (
        world.client.delete(f"/api/v1/admin/tokens/{token_id}", headers=world.admin_headers()).status_code
        == 200
    )
    assert world.client.get("/api/v1/submissions", headers=world.team_headers()).status_code == 401


def test_scopes_are_403(world: World) -> None:
    assert world.client.get("/api/v1/admin/teams", headers=world.team_headers()).status_code == 403
    assert world.client.get("/api/v1/submissions", headers=world.admin_headers()).status_code == 403
    assert world.client.get("/api/v1/admin/teams", headers=world.admin_headers()).status_code == 200


def test_a_team_must_be_approved_to_submit(world: World) -> None:
    _, pending_secret = add_team(world.factory, "pending team", Approval.pending)
    response = world.client.post(
        "/api/v1/submissions",
        headers=_bearer(pending_secret),
        files={"file": ("s.json", b"{}", "application/json")},
    )
    assert response.status_code == 403 and "approve" in response.json()["detail"]
    assert world.queued == []


def test_only_the_hash_of_a_token_is_stored(world: World) -> None:
    with world.session() as session:
        stored = session.scalars(select(ApiToken)).all()
    assert all(world.team_token not in (t.token_hash, t.prefix) for t in stored)
    assert hash_token(world.team_token) in {t.token_hash for t in stored}


def test_self_registration_gives_a_pending_team_and_a_working_token(world: World) -> None:
    response = world.client.post(
        "/api/v1/teams", json={"name": "gamma", "members": ["a", "b"], "affiliation": "U"}
    )
    assert response.status_code == 201
    body = response.json()
    assert body["team"]["approval"] == "pending"
    me = world.client.get("/api/v1/me", headers=_bearer(body["token"])).json()
    assert (me["team"], me["approval"]) == ("gamma", "pending")
    assert world.client.post("/api/v1/teams", json={"name": "gamma"}).status_code == 409
