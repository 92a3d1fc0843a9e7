"""Access control over the whole API, and rate limits: every write needs a token (registering a team aside),
every admin route refuses a team token (403) and no token (401); a team cannot see another team's unpublished submission, its per-token rows or its pictures;
failed authentications are limited per client address and uploads per token, each a 429 with Retry-After."""

from __future__ import annotations

import re

from server_testing import REFERENCE_SUBMISSIONS, World, add_team, submit_scored, uniform

from server.rate_limits import FAILED_AUTHENTICATIONS, UPLOADS_PER_TOKEN

HUMAN = (REFERENCE_SUBMISSIONS / "human.json").read_bytes()


def _concrete(path: str) -> str:
    return re.sub(r"\{[^}]+\}", "1", path)


def test_every_admin_route_refuses_a_team_token_and_no_token(world: World) -> None:
    schema = world.client.get("/openapi.json").json()
    admin_operations = [
        (method, _concrete(path))
        for path, operations in schema["paths"].items()
        if path.startswith("/api/v1/admin")
        for method in operations
    ]
    assert len(admin_operations) > 15
    for method, path in admin_operations:
        as_team = world.client.request(method, path, headers=world.team_headers())
        assert as_team.status_code == 403, (method, path, as_team.text)
        anonymous = world.client.request(method, path)
        assert anonymous.status_code == 401, (method, path, anonymous.text)


def test_every_write_needs_a_token_but_self_registration(world: World) -> None:
    schema = world.client.get("/openapi.json").json()
    writes = [
        (method, path, operation)
        for path, operations in schema["paths"].items()
        for method, operation in operations.items()
        if method in ("post", "put", "patch", "delete") and path != "/api/v1/teams"
    ]
    assert len(writes) > 15
    assert schema["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    for method, path, operation in writes:
        assert operation.get("security") == [{"HTTPBearer": []}], (method, path)  # the schema says so too
        response = world.client.request(method, _concrete(path))
        assert response.status_code == 401, (method, path, response.status_code, response.text)


def test_a_team_sees_nothing_of_another_teams_unpublished_submission(world: World) -> None:
    other_id, _ = add_team(world.factory, "beta")
    foreign = submit_scored(world, other_id, b"beta's entry", [uniform(0.5)])
    token = min(uniform(0.5))
    for path in (
        f"/api/v1/submissions/{foreign}",
        f"/api/v1/submissions/{foreign}/tokens",
        f"/api/v1/submissions/{foreign}/scenes/{token}.png",
        f"/api/v1/published/{foreign}",
    ):
        response = world.client.get(path, headers=world.team_headers())
        assert response.status_code == 404, (path, response.status_code, response.text)
        assert response.json()["detail"] != "Not Found", path  # the route exists: the submission is hidden
    patch = world.client.patch(
        f"/api/v1/submissions/{foreign}", headers=world.team_headers(), json={"method": "x"}
    )
    assert patch.status_code == 404


def test_failed_authentications_are_limited_per_client_address(world: World) -> None:
    allowed = FAILED_AUTHENTICATIONS.rate.amount
    for _ in range(allowed):
        assert (
            world.client.get("/api/v1/submissions", headers={"Authorization": "Bearer guess"}).status_code
            == 401
        )
    refused = world.client.get("/api/v1/submissions", headers={"Authorization": "Bearer guess"})
    assert refused.status_code == 429 and int(refused.headers["Retry-After"]) >= 1
    assert "failed authentications from your address" in refused.json()["detail"]
    # The address is refused whatever token it sends until the window moves on; public pages still answer.
    assert world.client.get("/api/v1/submissions", headers=world.team_headers()).status_code == 429
    assert world.client.get("/api/v1/leaderboard").status_code == 200


def test_uploads_are_limited_per_token(world: World) -> None:
    allowed = UPLOADS_PER_TOKEN.rate.amount
    answers = [
        world.client.post(
            "/api/v1/submissions:validate", headers=world.team_headers(), files={"file": ("h.json", HUMAN)}
        ).status_code
        for _ in range(allowed + 1)
    ]
    assert answers[:allowed] == [200] * allowed and answers[-1] == 429
    refused = world.client.post(
        "/api/v1/submissions", headers=world.team_headers(), files={"file": ("h.json", HUMAN)}
    )
    assert refused.status_code == 429 and "uploads with this token" in refused.json()["detail"]
    assert int(refused.headers["Retry-After"]) >= 1
    assert world.queued == []  # nothing was stored or sent
