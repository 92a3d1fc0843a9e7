"""Comparing a submission token by token: with the team's others, published entries and baselines of the same
split, never with another team's unpublished entry, and only on the tokens the team may see."""

from __future__ import annotations

from datetime import timedelta

from server_testing import World, add_phase, add_team, reference_tokens, score_run, submit_scored, uniform

from server.db import transaction
from server.models import Phase, Split, Submission, utc_now
from server.services.submissions import add_baselines


def _comparable(world: World, submission_id: int, headers: dict[str, str] | None = None) -> list[dict]:
    response = world.client.get(
        f"/api/v1/submissions/{submission_id}/comparable", headers=headers or world.team_headers()
    )
    assert response.status_code == 200, response.text
    return response.json()


def _rows(world: World, submission_id: int, other_id: int) -> tuple[int, dict]:
    response = world.client.get(
        f"/api/v1/submissions/{submission_id}/comparable/{other_id}/tokens",
        params={"version": "v1.1"},
        headers=world.team_headers(),
    )
    return response.status_code, response.json()


def _close(world: World, phase: str) -> None:
    with world.session() as session:
        session.query(Phase).filter_by(name=phase).one().closes_at = utc_now() - timedelta(seconds=1)
        session.commit()


def test_a_team_compares_with_its_own_published_entries_and_baselines_only(world: World) -> None:
    tokens = reference_tokens()
    mine = submit_scored(world, world.team_id, b"mine", [uniform(0.9)], "Mine")
    older = submit_scored(world, world.team_id, b"older", [uniform(0.5)], "Older")
    beta_id, _ = add_team(world.factory, "beta")
    unpublished = submit_scored(world, beta_id, b"beta-open", [uniform(0.7)], "Beta open")
    add_phase(world.factory, "past", closes_at=utc_now() + timedelta(days=1))
    published = submit_scored(world, beta_id, b"beta-past", [uniform(0.6)], "Beta past", phase="past")
    hidden = submit_scored(world, beta_id, b"beta-hidden", [uniform(0.2)], "Beta hidden", phase="past")
    with transaction(world.factory) as session:
        session.get(Submission, hidden).hidden = True
        split = session.query(Split).filter_by(name="reference").one()
        baseline = add_baselines(session, split, world.settings.submission_store)[0].id
    score_run(world.factory, baseline, [uniform(0.3)])

    assert {(entry["id"], entry["kind"]) for entry in _comparable(world, mine)} == {
        (older, "yours"),
        (baseline, "baseline"),
    }  # the past phase is still open: beta's entries are not published yet
    status, body = _rows(world, mine, published)
    assert status == 404 and "cannot be compared" in body["detail"]
    _close(world, "past")
    listed = {(entry["id"], entry["kind"]) for entry in _comparable(world, mine)}
    assert listed == {(older, "yours"), (published, "published"), (baseline, "baseline")}
    for other in (unpublished, hidden):
        assert _rows(world, mine, other)[0] == 404
    for other, score in ((older, 0.5), (published, 0.6), (baseline, 0.3)):
        status, rows = _rows(world, mine, other)
        assert status == 200 and len(rows) == len(tokens)
        assert {row["metrics"]["score"] for row in rows} == {score}
    # Another team's submission is not the team's to compare.
    assert (
        world.client.get(
            f"/api/v1/submissions/{published}/comparable", headers=world.team_headers()
        ).status_code
        == 404
    )


def test_a_comparison_shows_only_the_tokens_the_compared_submission_reveals(world: World) -> None:
    tokens = reference_tokens()
    add_phase(world.factory, "halves", split="halved", public_tokens=tokens[:10])
    mine = submit_scored(world, world.team_id, b"mine", [uniform(0.9)], "Mine", phase="halves")
    with transaction(world.factory) as session:
        split = session.query(Split).filter_by(name="halved").one()
        baseline = add_baselines(session, split, world.settings.submission_store)[0].id
    score_run(world.factory, baseline, [uniform(0.3)])
    status, rows = _rows(world, mine, baseline)
    assert status == 200 and sorted(row["token"] for row in rows) == tokens[:10]
    admin = world.client.get(
        f"/api/v1/admin/submissions/{mine}/comparable/{baseline}/tokens", headers=world.admin_headers()
    )
    assert admin.status_code == 200 and len(admin.json()) == len(tokens)


def test_a_published_entry_compares_with_published_entries_and_baselines(world: World) -> None:
    mine = submit_scored(world, world.team_id, b"mine", [uniform(0.9)], "Mine")
    beta_id, _ = add_team(world.factory, "beta")
    theirs = submit_scored(world, beta_id, b"beta", [uniform(0.6)], "Beta")
    assert world.client.get(f"/api/v1/published/{mine}/comparable").status_code == 404
    _close(world, world.phase)
    listed = world.client.get(f"/api/v1/published/{mine}/comparable").json()
    assert [(entry["id"], entry["kind"]) for entry in listed] == [(theirs, "published")]
    rows = world.client.get(f"/api/v1/published/{mine}/comparable/{theirs}/tokens").json()
    assert {row["metrics"]["score"] for row in rows} == {0.6}
