"""Uploads into an S3 object store (CI's moto server): the file and its parsed trajectories are objects before
the row that names them exists; with the store unreachable an upload is a 503 saying nothing was stored, no
row is left behind, and the board is still served."""

from __future__ import annotations

import hashlib

import pytest
from object_stores import fresh_s3_store
from server_testing import REFERENCE_SUBMISSIONS, World
from worker_testing import free_port

from server.main import STORE_DOWN
from server.models import Submission
from server.settings import Settings
from server.storage import TRAJECTORIES_SUFFIX, stored_name

HUMAN = (REFERENCE_SUBMISSIONS / "human.json").read_bytes()


@pytest.fixture
def server_settings(server_settings: Settings) -> Settings:
    return server_settings.model_copy(update={"storage_url": fresh_s3_store().url})


def _post(world: World, data: bytes = HUMAN):
    return world.client.post(
        "/api/v1/submissions", headers=world.team_headers(), files={"file": ("human.json", data)}
    )


def _rows(world: World) -> int:
    with world.factory() as session:
        return session.query(Submission).count()


def test_an_upload_is_stored_in_the_object_store_by_its_sha256(world: World) -> None:
    assert _post(world).status_code == 202
    name = stored_name(hashlib.sha256(HUMAN).hexdigest())
    store = world.settings.submission_store
    assert store.url.startswith("s3://") and store.url.endswith("/submissions")
    assert store.get(name) == HUMAN
    assert store.keys("") == sorted([name, f"{name}{TRAJECTORIES_SUFFIX}"])
    assert not world.settings.storage_dir.exists()  # nothing on the API's disk


def test_with_the_store_unreachable_an_upload_is_a_503_and_leaves_no_row(
    world: World, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{free_port()}")
    response = _post(world)
    assert response.status_code == 503, response.text
    assert response.json() == {"detail": STORE_DOWN} and response.headers["Retry-After"]
    assert _rows(world) == 0 and world.queued == []
    board = world.client.get("/api/v1/leaderboard", params={"phase": "test"})
    assert board.status_code == 200, board.text
    monkeypatch.undo()  # the store is back: the same upload goes through
    assert _post(world).status_code == 202 and _rows(world) == 1
