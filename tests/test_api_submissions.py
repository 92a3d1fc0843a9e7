"""Upload API over HTTP: 202 with an id and a queued task, 422 listing every problem, dry-run validation,
idempotency, duplicates, quota answers (429 with what and when), status and metadata edits; a bad request
never stores or changes anything."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

from server_testing import REFERENCE_SUBMISSIONS, World, add_phase

from navsim_lb.client import refusal_lines
from scorer.submission import load_submission
from server.storage import read_trajectories, stored_name

HUMAN = (REFERENCE_SUBMISSIONS / "human.json").read_bytes()


def _post(world: World, data: bytes, name: str = "human.json", key: str | None = None, **form: str):
    headers = world.team_headers() | ({"Idempotency-Key": key} if key else {})
    return world.client.post("/api/v1/submissions", headers=headers, files={"file": (name, data)}, data=form)


def _state(world: World) -> tuple[list, list[Path]]:
    """Everything stored: the submissions (as the API shows them) and the stored files."""
    listing = world.client.get("/api/v1/submissions", headers=world.team_headers()).json()
    return listing, sorted(p for p in Path(world.settings.storage_dir).rglob("*") if p.is_file())


def _broken() -> bytes:
    """The human submission with three problems: a missing token, a wrong shape, a non-finite value."""
    document = json.loads(HUMAN)
    tokens = sorted(document["predictions"])
    del document["predictions"][tokens[0]]
    document["predictions"][tokens[1]] = document["predictions"][tokens[1]][:5]
    document["predictions"][tokens[2]][3][0] = math.inf
    return json.dumps(document, allow_nan=True).encode()


def test_upload_is_accepted_queued_and_shown(world: World) -> None:
    response = _post(world, HUMAN, method="Our planner", code_url="https://example.org/code")
    assert response.status_code == 202
    body = response.json()
    assert body["status"] == "queued" and body["replayed"] is False
    assert world.queued == [body["id"]]
    assert response.headers["Location"].endswith(f"/api/v1/submissions/{body['id']}")
    detail = world.client.get(f"/api/v1/submissions/{body['id']}", headers=world.team_headers()).json()
    assert (detail["method"], detail["code_url"], detail["progress"], detail["seed_count"]) == (
        "Our planner",
        "https://example.org/code",
        0,
        1,
    )
    assert detail["authors"] == "reference run"  # from the file when no form field overrides it
    # Beside the file, the trajectories its check parsed, for the workers and the pictures.
    stored = hashlib.sha256(HUMAN).hexdigest()
    parsed = read_trajectories(world.settings.submission_store, stored_name(stored), stored)
    human = load_submission(HUMAN).seeds
    assert parsed is not None and list(parsed[0]) == list(human[0])
    assert all(parsed[0][token].tobytes() == poses.tobytes() for token, poses in human[0].items())


def test_every_problem_is_listed_and_nothing_is_stored(world: World) -> None:
    before = _state(world)
    response = _post(world, _broken())
    assert response.status_code == 422
    problems = response.json()["problems"]
    assert len(problems) >= 3
    assert all(set(p) == {"token", "field", "message"} for p in problems)
    tokens = sorted(json.loads(HUMAN)["predictions"])
    assert set(tokens[:3]) <= {p["token"] for p in problems}
    assert _state(world) == before and world.queued == []
    assert _post(world, b"not json at all", "x.json").status_code == 422
    assert _state(world) == before


def test_links_must_be_web_addresses_and_nothing_is_stored_otherwise(world: World) -> None:
    before = _state(world)
    response = _post(world, HUMAN, tech_report_url="javascript:alert(1)", code_url="https://example.org/x")
    assert response.status_code == 422
    assert response.json()["problems"] == [
        {
            "token": None,
            "field": "tech_report_url",
            "message": "tech_report_url must be an http:// or https:// address",
        }
    ]
    assert _state(world) == before and world.queued == []
    assert _post(world, HUMAN, code_url="ftp://example.org").json()["problems"][0]["field"] == "code_url"


def test_dry_run_validation_stores_nothing(world: World) -> None:
    before = _state(world)
    ok = world.client.post(
        "/api/v1/submissions:validate", headers=world.team_headers(), files={"file": ("human.json", HUMAN)}
    )
    assert ok.status_code == 200 and ok.json()["valid"] is True and ok.json()["token_count"] == 40
    bad = world.client.post(
        "/api/v1/submissions:validate",
        headers=world.team_headers(),
        files={"file": ("human.json", _broken())},
    )
    assert bad.status_code == 422 and len(bad.json()["problems"]) >= 3
    assert _state(world) == before and world.queued == []


def test_idempotency_key_replays_the_first_answer(world: World) -> None:
    first = _post(world, HUMAN, key="upload-1")
    again = _post(world, HUMAN, key="upload-1")
    assert (first.status_code, again.status_code) == (202, 202)
    assert again.json()["id"] == first.json()["id"] and again.json()["replayed"] is True
    assert world.queued == [first.json()["id"]]
    other = _post(world, (REFERENCE_SUBMISSIONS / "stop.json").read_bytes(), "stop.json", key="upload-1")
    assert other.status_code == 409 and other.json()["submission_id"] == first.json()["id"]


def test_the_same_file_is_refused_with_the_earlier_id(world: World) -> None:
    first = _post(world, HUMAN).json()["id"]
    duplicate = _post(world, HUMAN)
    assert duplicate.status_code == 409 and duplicate.json()["submission_id"] == first
    assert world.queued == [first]


def test_quota_exhaustion_says_what_and_when(world: World) -> None:
    add_phase(world.factory, "daily", per_day=1)
    assert _post(world, HUMAN, phase="daily").status_code == 202
    before = _state(world)
    response = _post(world, (REFERENCE_SUBMISSIONS / "stop.json").read_bytes(), "stop.json", phase="daily")
    assert response.status_code == 429
    body = response.json()
    assert (body["quota"], body["limit"], body["used"]) == ("per_day", 1, 1)
    assert body["resets_at"].endswith("T00:00:00Z") and int(response.headers["Retry-After"]) > 0
    # Its reset is stated once, as a person reads a time (the field and the header are for programs).
    reset = body["resets_at"][:16].replace("T", " ")
    assert body["detail"].endswith(f"it resets at {reset} UTC") and body["detail"].count("reset") == 1
    assert refusal_lines(response)[-1] == body["detail"]  # `navsim-lb submit` adds no "retry after"
    assert _state(world) == before
    invalid = _post(world, _broken(), phase="daily")
    assert invalid.status_code == 422  # an invalid file is refused before quotas and uses none


def test_patch_edits_metadata_only_of_own_submissions(world: World) -> None:
    submission_id = _post(world, HUMAN).json()["id"]
    response = world.client.patch(
        f"/api/v1/submissions/{submission_id}",
        headers=world.team_headers(),
        json={"method": "Renamed", "hidden": True},
    )
    assert response.status_code == 200 and (response.json()["method"], response.json()["hidden"]) == (
        "Renamed",
        True,
    )
    assert (
        world.client.patch(
            f"/api/v1/submissions/{submission_id}", headers=world.team_headers(), json={"status": "scored"}
        ).status_code
        == 422
    )
    assert (
        world.client.get(f"/api/v1/submissions/{submission_id}", headers=world.team_headers()).json()[
            "status"
        ]
        == "queued"
    )
    beta = world.client.post("/api/v1/teams", json={"name": "beta"}).json()["token"]
    foreign = world.client.get(
        f"/api/v1/submissions/{submission_id}", headers={"Authorization": f"Bearer {beta}"}
    )
    assert foreign.status_code == 404


def test_oversized_uploads_are_refused(world: World) -> None:
    world.client.app.state.settings.max_upload_bytes = 1000
    response = _post(world, HUMAN)
    assert response.status_code == 413 and world.queued == []
