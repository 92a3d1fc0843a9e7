"""Admin API: team approval, tokens and quotas, re-run, cancel, rescore-all with its rank report, export, and
an audit entry for every action; plus the public splits and health routes."""

from __future__ import annotations

import csv
import io

import pytest
from server_testing import (
    REFERENCE_DIR,
    World,
    add_team,
    phase_row,
    score_run,
    submit_scored,
    team_row,
    uniform,
    upload_of,
)
from sqlalchemy import delete

from server.db import transaction
from server.models import Approval, Submission, Summary, utc_now
from server.services.submissions import create_submission
from server.services.workers import record_heartbeat


def _audit_actions(world: World) -> list[str]:
    entries = world.client.get("/api/v1/admin/audit", headers=world.admin_headers()).json()
    return [entry["action"] for entry in reversed(entries)]


def test_team_approval_tokens_and_quotas_are_audited(world: World) -> None:
    team_id, secret = add_team(world.factory, "newcomers", Approval.pending)
    teams = world.client.get("/api/v1/admin/teams", headers=world.admin_headers()).json()
    assert teams[0]["name"] == "newcomers" and teams[0]["approval"] == "pending"  # pending teams first
    assert (
        world.client.post(f"/api/v1/admin/teams/{team_id}/approve", headers=world.admin_headers()).status_code
        == 200
    )
    created = world.client.post(
        f"/api/v1/admin/teams/{team_id}/tokens", json={"name": "ci"}, headers=world.admin_headers()
    )
    assert created.status_code == 201 and created.json()["token"].startswith("nlb_")
    listed = world.client.get(f"/api/v1/admin/teams/{team_id}/tokens", headers=world.admin_headers()).json()
    assert len(listed) == 2 and all("token" not in row for row in listed)
    quota = world.client.put(
        f"/api/v1/admin/teams/{team_id}/quotas",
        json={"phase": "test", "per_day": 3},
        headers=world.admin_headers(),
    )
    assert quota.status_code == 200
    me = world.client.get("/api/v1/me", headers={"Authorization": f"Bearer {secret}"}).json()
    assert {(q["quota"], q["limit"]) for q in me["quotas"]} >= {("per_day", 3)}
    assert _audit_actions(world) == ["approve_team", "create_token", "set_quota"]
    entry = world.client.get("/api/v1/admin/audit", headers=world.admin_headers()).json()[0]
    assert entry["actor"].startswith("admin token nlb_") and entry["details"]["per_day"] == 3


def test_rerun_and_cancel(world: World) -> None:
    scored = submit_scored(world, world.team_id, b"a", [uniform(0.5)])
    rerun = world.client.post(f"/api/v1/admin/submissions/{scored}/rerun", headers=world.admin_headers())
    assert rerun.status_code == 200 and (rerun.json()["status"], rerun.json()["run"]) == ("queued", 2)
    assert world.queued == [scored]
    assert (
        world.client.post(
            f"/api/v1/admin/submissions/{scored}/rerun", headers=world.admin_headers()
        ).status_code
        == 409
    )
    cancelled = world.client.post(f"/api/v1/admin/submissions/{scored}/cancel", headers=world.admin_headers())
    assert (
        cancelled.status_code == 200
        and cancelled.json()["status"] == "cancelled"
        and not cancelled.json()["charged"]
    )
    assert (
        world.client.post(
            f"/api/v1/admin/submissions/{scored}/cancel", headers=world.admin_headers()
        ).status_code
        == 409
    )
    assert _audit_actions(world) == ["rerun", "cancel"]


def test_rescore_all_reports_rank_changes(world: World) -> None:
    beta, _ = add_team(world.factory, "beta")
    gamma, _ = add_team(world.factory, "gamma")
    a = submit_scored(world, world.team_id, b"a", [uniform(0.9)], "A")
    b = submit_scored(world, beta, b"b", [uniform(0.8)], "B")
    c = submit_scored(world, gamma, b"c", [uniform(0.7)], "C")
    started = world.client.post(
        "/api/v1/admin/rescore", json={"version": "v1.1"}, headers=world.admin_headers()
    )
    assert started.status_code == 202 and started.json()["queued"] == 3
    assert sorted(world.queued) == sorted([a, b, c])
    pending = world.client.get(
        f"/api/v1/admin/rescores/{started.json()['id']}", headers=world.admin_headers()
    ).json()
    assert pending["complete"] is False and pending["pending"] == 3 and pending["moved"] == []
    # The new engine swaps the first two teams.
    for submission_id, score in ((a, 0.8), (b, 0.85), (c, 0.7)):
        score_run(world.factory, submission_id, [uniform(score)])
    report = world.client.get(started.json()["report"], headers=world.admin_headers()).json()
    assert report["complete"] is True and report["entries"] == 3
    assert [(m["team"], m["rank_before"], m["rank_after"]) for m in report["moved"]] == [
        ("beta", 2, 1),
        ("alpha", 1, 2),
    ]
    assert report["kendall_tau"] == pytest.approx(1 / 3)
    assert "rescore_all" in _audit_actions(world)


def test_rescoring_under_a_version_new_on_the_board_reports_ranks_against_the_default_version(
    world: World,
) -> None:
    """Entries scored before v2.2 was on the board have no v2.2 summary: "rescore all under v2.2" compares the
    v2.2 ranking after with the v1.1 ranking before (or with the version the organiser names)."""
    beta, _ = add_team(world.factory, "beta")
    a = submit_scored(world, world.team_id, b"a", [uniform(0.9)], "A")
    b = submit_scored(world, beta, b"b", [uniform(0.8)], "B")
    with transaction(world.factory) as session:  # as stored before v2.2 was on the board
        session.execute(delete(Summary).where(Summary.metric_version == "v2.2"))
    assert _board_rows(world, "v2.2") == []
    started = world.client.post(
        "/api/v1/admin/rescore", json={"version": "v2.2"}, headers=world.admin_headers()
    )
    assert started.status_code == 202 and started.json()["queued"] == 2
    for submission_id, score in ((a, 0.7), (b, 0.75)):
        score_run(world.factory, submission_id, [uniform(score)])
    report = world.client.get(started.json()["report"], headers=world.admin_headers()).json()
    assert (report["version"], report["before_version"]) == ("v2.2", "v1.1")
    assert (report["score_label"], report["before_score_label"]) == ("EPDMS", "PDMS")
    assert [(m["team"], m["rank_before"], m["rank_after"]) for m in report["moved"]] == [
        ("beta", 2, 1),
        ("alpha", 1, 2),
    ]
    named = world.client.post(
        "/api/v1/admin/rescore",
        json={"version": "v2.2", "compare_with": "v1.0"},
        headers=world.admin_headers(),
    )
    again = world.client.get(named.json()["report"], headers=world.admin_headers()).json()
    assert again["before_version"] == "v1.0" and again["complete"] is False


def _board_rows(world: World, version: str) -> list[dict]:
    response = world.client.get("/api/v1/leaderboard", params={"version": version})
    assert response.status_code == 200, response.text
    return list(response.json()["rows"])


def test_export_lists_every_scored_submission_with_flags(world: World) -> None:
    first = submit_scored(world, world.team_id, b"a", [uniform(0.6)], "first")
    second = submit_scored(world, world.team_id, b"b", [uniform(0.7)], "second")
    world.client.post(
        f"/api/v1/admin/submissions/{first}/hide", json={"hidden": True}, headers=world.admin_headers()
    )
    text = world.client.get("/api/v1/admin/export", params={"format": "csv"}, headers=world.admin_headers())
    assert text.status_code == 200 and text.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(text.text)))
    assert [(int(r["submission_id"]), r["method"], r["admin_hidden"]) for r in rows] == [
        (first, "first", "True"),
        (second, "second", "False"),
    ]
    assert float(rows[1]["score"]) == pytest.approx(0.7) and "ego_progress" in rows[0]
    body = world.client.get(
        "/api/v1/admin/export", params={"format": "json", "version": "v1.0"}, headers=world.admin_headers()
    ).json()
    assert body["version"] == "v1.0" and [r["submission_id"] for r in body["rows"]] == [first, second]


def test_admin_sees_failures_in_detail_teams_only_the_summary(world: World) -> None:
    from server.models import FailureKind
    from server.runs import claim_submission, mark_failed

    with transaction(world.factory) as session:
        submission, _ = create_submission(
            session,
            team_row(session, world.team_id),
            phase_row(session, "test"),
            upload_of(b"x"),
            world.settings.submission_store,
        )
        run = claim_submission(session, submission.id, "w")
        mark_failed(
            session,
            submission.id,
            run,
            FailureKind.infrastructure,
            "worker lost",
            detail="Traceback ... /data/hidden/scene.json",
        )
        submission_id = submission.id
    team_view = world.client.get(f"/api/v1/submissions/{submission_id}", headers=world.team_headers()).json()
    assert team_view["status"] == "failed" and "refunded" in team_view["error"]
    assert "Traceback" not in str(team_view) and "/data/hidden" not in str(team_view)
    admin_view = world.client.get(
        f"/api/v1/admin/submissions/{submission_id}", headers=world.admin_headers()
    ).json()
    assert (
        admin_view["error_detail"].startswith("Traceback") and admin_view["failure_kind"] == "infrastructure"
    )


def test_splits_and_health(world: World) -> None:
    splits = world.client.get("/api/v1/splits").json()
    assert [(s["name"], s["token_count"], s["subsets"]) for s in splits] == [("reference", 40, {"all": 40})]
    assert splits[0]["phases"][0]["name"] == "test" and splits[0]["phases"][0]["open"] is True
    health = world.client.get("/api/v1/health")
    assert health.status_code == 200
    body = health.json()
    assert body["database"]["ok"] is True and body["broker"]["ok"] is True
    # No worker runs here, and the embedded broker cannot ping: the database's heartbeats say so.
    assert (
        body["status"] == "degraded"
        and body["workers"]["ok"] is False
        and "(none)" in body["workers"]["detail"]
    )
    with transaction(world.factory) as session:
        record_heartbeat(session, "celery@test", utc_now())
    body = world.client.get("/api/v1/health").json()
    assert body["status"] == "ok" and body["workers"]["names"] == ["celery@test"]


def test_health_degrades_when_the_broker_is_down(world: World) -> None:
    world.client.app.state.broker_status = lambda settings: {"ok": False, "detail": "connection refused"}
    body = world.client.get("/api/v1/health").json()
    assert body["status"] == "degraded" and body["broker"]["detail"] == "connection refused"


def test_register_split_scores_its_baselines(world: World) -> None:
    response = world.client.post(
        "/api/v1/admin/splits",
        headers=world.admin_headers(),
        json={"name": "again", "directory": str(REFERENCE_DIR)},
    )
    assert response.status_code == 201
    body = response.json()
    assert body["token_count"] == 40 and len(body["content_hash"]) == 64
    assert sorted(world.queued) == sorted(body["baseline_submissions"])
    with world.session() as session:
        baselines = [session.get(Submission, i) for i in body["baseline_submissions"]]
        assert {(s.method, s.is_baseline, s.charged, s.team.name) for s in baselines} == {
            ("Constant Velocity", True, False, "NAVSIM baselines"),
            ("Human", True, False, "NAVSIM baselines"),
        }
    assert (
        world.client.post(
            "/api/v1/admin/splits",
            headers=world.admin_headers(),
            json={"name": "again", "directory": str(REFERENCE_DIR)},
        ).status_code
        == 409
    )


def test_numbers_beyond_the_sql_integers_are_refused_naming_the_field(world: World) -> None:
    huge = 2**63
    headers = world.admin_headers()
    answers = {
        "team_id": world.client.post(f"/api/v1/admin/teams/{huge}/approve", headers=headers),
        "rescore_id": world.client.get(f"/api/v1/admin/rescores/{huge}", headers=headers),
        "offset": world.client.get("/api/v1/admin/submissions", params={"offset": huge}, headers=headers),
        "total": world.client.put(
            f"/api/v1/admin/teams/{world.team_id}/quotas",
            json={"phase": "test", "total": huge},
            headers=headers,
        ),
        "submission_id": world.client.get(f"/api/v1/submissions/{huge}", headers=world.team_headers()),
    }
    for field, answer in answers.items():
        assert answer.status_code == 422, (field, answer.text)
        assert field in answer.text and "2147483647" in answer.text, answer.text


def test_unknown_status_and_control_characters_in_names_are_refused(world: World) -> None:
    listed = world.client.get(
        "/api/v1/admin/submissions", params={"status": "done"}, headers=world.admin_headers()
    )
    assert listed.status_code == 422 and "status" in listed.text and "scored" in listed.text
    phase = world.client.post(
        "/api/v1/admin/phases", json={"name": "test\x00", "split": "reference"}, headers=world.admin_headers()
    )
    assert phase.status_code == 422 and "control characters" in phase.text
    team = world.client.post(
        "/api/v1/admin/teams", json={"name": "\x1b[31mred"}, headers=world.admin_headers()
    )
    assert team.status_code == 422 and "control characters" in team.text


def test_export_of_a_phase_with_a_non_ascii_name_downloads(world: World) -> None:
    created = world.client.post(
        "/api/v1/admin/phases",
        json={"name": "Prüfung – 测试", "split": "reference"},
        headers=world.admin_headers(),
    )
    assert created.status_code in (200, 201), created.text
    answer = world.client.get(
        "/api/v1/admin/export", params={"phase": "Prüfung – 测试"}, headers=world.admin_headers()
    )
    assert answer.status_code == 200, answer.text
    disposition = answer.headers["content-disposition"]
    assert 'filename="navsim-lb-Pr_fung_____-v1.1-all.csv"' in disposition
    assert (
        "filename*=UTF-8''navsim-lb-Pr%C3%BCfung%20%E2%80%93%20%E6%B5%8B%E8%AF%95-v1.1-all.csv" in disposition
    )


def test_times_need_a_time_zone_and_a_utc_equivalent(world: World) -> None:
    headers = world.admin_headers()
    naive = world.client.post(
        "/api/v1/admin/phases",
        json={"name": "naive", "split": "reference", "opens_at": "2026-01-01T00:00:00"},
        headers=headers,
    )
    assert naive.status_code == 422 and "opens_at" in naive.text and "timezone" in naive.text
    beyond = world.client.post(
        f"/api/v1/admin/teams/{world.team_id}/tokens",
        json={"name": "far", "expires_at": "9999-12-31T23:59:00-05:00"},
        headers=headers,
    )
    assert beyond.status_code == 422 and "expires_at" in beyond.text and "out of range" in beyond.text
    aware = world.client.post(
        "/api/v1/admin/phases",
        json={"name": "aware", "split": "reference", "opens_at": "2026-01-01T02:00:00+02:00"},
        headers=headers,
    )
    assert aware.status_code in (200, 201) and aware.json()["opens_at"].startswith("2026-01-01T00:00:00")


def test_a_split_directory_with_control_characters_is_refused(world: World) -> None:
    answer = world.client.post(
        "/api/v1/admin/splits",
        json={"name": "nul", "directory": "/data/\x00split"},
        headers=world.admin_headers(),
    )
    assert answer.status_code == 422 and "directory" in answer.text and "control characters" in answer.text


def test_an_unreadable_split_directory_is_refused_with_the_reason(world: World) -> None:
    answer = world.client.post(
        "/api/v1/admin/splits", json={"name": "long", "directory": "x" * 300}, headers=world.admin_headers()
    )
    assert answer.status_code == 409 and "cannot be read (File name too long)" in answer.text
