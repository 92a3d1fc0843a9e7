"""Drill-down pictures over the API: a team sees them only for its own scored submissions, on splits whose
scenes are public and tokens it may see; organisers see every scene; a picture is rendered once."""

from __future__ import annotations

import json
import re
from datetime import timedelta

from server_testing import REFERENCE_SUBMISSIONS, World, add_team, submit_scored, uniform

from server.models import Phase, Split, Submission, utc_now

HUMAN = (REFERENCE_SUBMISSIONS / "human.json").read_bytes()
TOKEN = min(json.loads(HUMAN)["predictions"])


def _scenes_public(world: World, public: bool) -> None:
    with world.session() as session:
        for split in session.query(Split).all():
            split.scenes_public = public
        session.commit()


def _picture(world: World, submission_id: int, token: str = TOKEN, admin: bool = False, **params: str):
    prefix = "/api/v1/admin" if admin else "/api/v1"
    headers = world.admin_headers() if admin else world.team_headers()
    return world.client.get(
        f"{prefix}/submissions/{submission_id}/scenes/{token}.png", params=params, headers=headers
    )


def test_pictures_follow_the_splits_scene_policy_and_the_submissions_owner(world: World) -> None:
    submission_id = submit_scored(world, world.team_id, HUMAN, [uniform(0.9)], "Human")
    hidden = _picture(world, submission_id)
    assert hidden.status_code == 403 and "only the organisers see them" in hidden.json()["detail"]
    organiser = _picture(world, submission_id, admin=True)
    assert organiser.status_code == 200 and organiser.headers["content-type"] == "image/png"
    assert organiser.content.startswith(b"\x89PNG")

    _scenes_public(world, True)
    shown = _picture(world, submission_id, version="v1.0")
    assert shown.status_code == 200 and shown.content.startswith(b"\x89PNG")
    assert _picture(world, submission_id, token="0123456789abcdef").status_code == 404
    assert _picture(world, submission_id, token="..%2Fetc").status_code in (404, 422)
    assert _picture(world, submission_id, version="v9").status_code == 422
    assert _picture(world, submission_id, seed="3").status_code == 404

    _, beta_token = add_team(world.factory, "beta")
    other = world.client.get(
        f"/api/v1/submissions/{submission_id}/scenes/{TOKEN}.png",
        headers={"Authorization": f"Bearer {beta_token}"},
    )
    assert other.status_code == 404  # another team's submission does not exist for beta


def test_a_picture_needs_a_scored_submission_and_is_rendered_once(world: World) -> None:
    _scenes_public(world, True)
    submission_id = submit_scored(world, world.team_id, HUMAN, [uniform(0.9)], "Human")
    first = _picture(world, submission_id)
    assert first.status_code == 200
    pictures = list((world.settings.data_dir / "pictures").iterdir())
    assert len(pictures) == 1
    pictures[0].write_bytes(b"\x89PNG cached")  # served from disk from now on
    assert _picture(world, submission_id).content == b"\x89PNG cached"

    with world.session() as session:
        session.get(Submission, submission_id).status = "running"
        session.commit()
    waiting = _picture(world, submission_id)
    assert waiting.status_code == 409 and "once it is scored" in waiting.json()["detail"]


def test_organisers_read_every_tokens_rows_and_teams_only_their_own(world: World) -> None:
    submission_id = submit_scored(world, world.team_id, HUMAN, [uniform(0.9)], "Human")
    admin = world.client.get(
        f"/api/v1/admin/submissions/{submission_id}/tokens", headers=world.admin_headers()
    )
    assert admin.status_code == 200 and len(admin.json()) == len(json.loads(HUMAN)["predictions"])
    assert world.client.get(
        f"/api/v1/admin/submissions/{submission_id}/tokens", headers=world.team_headers()
    ).status_code in (401, 403)


def test_entries_are_published_to_everyone_once_their_phase_has_closed(world: World) -> None:
    _scenes_public(world, True)
    submission_id = submit_scored(world, world.team_id, HUMAN, [uniform(0.9)], "Human")
    closed = world.client.get(f"/api/v1/published/{submission_id}")
    assert closed.status_code == 404 and "public once their phase has closed" in closed.json()["detail"]
    assert f'/submissions/{submission_id}">Human</a>' not in world.client.get("/").text
    with world.session() as session:
        session.query(Phase).filter_by(name=world.phase).one().closes_at = utc_now() - timedelta(seconds=1)
        session.commit()
    entry = world.client.get(f"/api/v1/published/{submission_id}")
    assert entry.status_code == 200 and entry.json()["method"] == "Human"
    rows = world.client.get(f"/api/v1/published/{submission_id}/tokens", params={"version": "v1.0"}).json()
    assert len(rows) == len(json.loads(HUMAN)["predictions"]) and {r["metric_version"] for r in rows} == {
        "v1.0"
    }
    picture = world.client.get(f"/api/v1/published/{submission_id}/scenes/{TOKEN}.png")
    assert picture.status_code == 200 and picture.content.startswith(b"\x89PNG")
    board = world.client.get("/", params={"phase": world.phase}).text
    assert f'/submissions/{submission_id}">Human</a>' in board
    assert re.search(
        f'<tr[^>]* data-href="[^"]*/submissions/{submission_id}"', board
    )  # the whole row opens it
    with world.session() as session:
        session.get(Submission, submission_id).hidden = True  # the team takes it off the board
        session.commit()
    assert world.client.get(f"/api/v1/published/{submission_id}").status_code == 404


def test_a_picture_follows_the_chosen_version_and_layout(world: World) -> None:
    _scenes_public(world, True)
    submission_id = submit_scored(world, world.team_id, HUMAN, [uniform(0.9)], "Human")
    pictures = {
        (version, layout): _picture(world, submission_id, version=version, layout=layout)
        for version in ("v1.1", "v2.2")
        for layout in ("wide", "narrow")
    }
    assert all(picture.status_code == 200 for picture in pictures.values())
    widths = {key: int.from_bytes(picture.content[16:20], "big") for key, picture in pictures.items()}
    assert widths == {
        ("v1.1", "wide"): 1100,
        ("v2.2", "wide"): 1100,
        ("v1.1", "narrow"): 360,
        ("v2.2", "narrow"): 360,
    }
    assert len({picture.content for picture in pictures.values()}) == 4  # each version drawn as scored
    assert len(list((world.settings.data_dir / "pictures").iterdir())) == 4
    assert _picture(world, submission_id, layout="huge").status_code == 422
