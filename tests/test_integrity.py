"""Integrity checks for organisers on the reference scenes: a leaked log, a copy of another team's entry and a
team probing the hidden set are flagged with their evidence; honest entries are not; teams never see flags."""

from __future__ import annotations

import json
import logging
from datetime import timedelta
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import typer
from server_testing import REFERENCE_DIR, World, add_team, phase_row, team_row
from typer.testing import CliRunner

from scorer.baselines import baseline_submission
from scorer.geometry import FloatArray
from scorer.submission import Submission as Predictions
from scorer.submission import SubmissionMetadata, dump_submission_json
from server.cli import register
from server.db import transaction
from server.models import ChunkState, IntegrityCheck, ScoringChunk, Status, Submission, utc_now
from server.runs import check_integrity_after_run
from server.services import integrity
from server.services.integrity import AFTER_COMMIT, integrity_report
from server.services.integrity_checks import LEAK_MEDIAN_ADE_M, MOVING_M, displacements
from server.services.splits import split_tokens
from server.services.submissions import create_submission
from server.services.validation import validate_upload
from server.settings import get_settings

Seed = dict[str, FloatArray]


@cache
def _baseline_seed(kind: str) -> Seed:
    return dict(baseline_submission(Path(REFERENCE_DIR), kind, kind).seeds[0])


def _baseline(kind: str) -> Seed:
    return dict(_baseline_seed(kind))


def _submit(world: World, team_id: int, seeds: Seed | tuple[Seed, ...], method: str) -> int:
    """Store an entry of `team_id` as an upload would (its file and the trajectories its check parsed)."""
    with transaction(world.factory) as session:
        split = phase_row(session, world.phase).split
        per_seed = seeds if isinstance(seeds, tuple) else (seeds,)
        predictions = Predictions(SubmissionMetadata(team_name=method, method=method), per_seed)
        upload = validate_upload(
            dump_submission_json(predictions), f"{method}.json", split_tokens(split), {"method": method}
        )
        submission, _ = create_submission(
            session,
            team_row(session, team_id),
            phase_row(session, world.phase),
            upload,
            world.settings.submission_store,
        )
        return submission.id


def _noisy(seed: Seed, sigma: float, rng_seed: int) -> Seed:
    rng = np.random.default_rng(rng_seed)
    return {token: poses + rng.normal(0.0, sigma, poses.shape) for token, poses in seed.items()}


def _check(world: World) -> dict:
    started = world.client.post("/api/v1/admin/integrity/checks", json={}, headers=world.admin_headers())
    assert started.status_code == 202, started.text
    report = world.client.get("/api/v1/admin/integrity", headers=world.admin_headers())
    assert report.status_code == 200
    (check,) = report.json()["checks"]
    assert check["finished_at"] is not None and check["error"] is None
    return check


def test_honest_entries_are_not_flagged_and_their_ade_is_far_above_the_threshold(world: World) -> None:
    human = _baseline("human")
    noisy, straight = _noisy(human, 0.3, 7), _baseline("constant-velocity")
    for name, seed in (("noisy", noisy), ("straight", straight)):
        team_id, _ = add_team(world.factory, name)
        _submit(world, team_id, seed, name)
        tokens = sorted(human)
        ade = displacements(
            np.stack([seed[t][:, :2] for t in tokens]), np.stack([human[t][:, :2] for t in tokens])
        ).mean(axis=1)
        moving = np.array(
            [np.linalg.norm(np.diff(human[t][:, :2], axis=0), axis=1).sum() >= MOVING_M for t in tokens]
        )
        assert np.median(ade[moving]) > 4 * LEAK_MEDIAN_ADE_M  # honest figures sit well above the line
    check = _check(world)
    assert check["entries"] == 2 and check["flags"] == []


def test_a_leaked_log_a_cross_team_copy_and_probing_are_flagged_with_evidence(world: World) -> None:
    human = _baseline("human")
    leaked = {token: poses.astype(np.float32).astype(np.float64) for token, poses in human.items()}
    leaker, _ = add_team(world.factory, "leaker")
    leak_id = _submit(world, leaker, leaked, "oracle")
    honest, _ = add_team(world.factory, "honest")
    original = _noisy(human, 0.4, 1)
    original_id = _submit(world, honest, original, "original")
    copier, copier_token = add_team(world.factory, "copier")
    copy_id = _submit(
        world, copier, _noisy(original, 0.001, 2), "copy"
    )  # a millimetre of noise hides nothing
    prober, _ = add_team(world.factory, "prober")
    base = _noisy(human, 0.5, 3)
    tokens = sorted(base)
    probes = [_submit(world, prober, base, "probe 0")]
    for step in range(1, 4):  # each upload moves one more token
        changed = dict(base) | {tokens[i]: base[tokens[i]] + 2.0 for i in range(step)}
        probes.append(_submit(world, prober, changed, f"probe {step}"))

    check = _check(world)
    by_kind: dict[str, list[dict]] = {}
    for flag in check["flags"]:
        by_kind.setdefault(flag["kind"], []).append(flag)

    (leak,) = by_kind["leaked_log"]
    assert leak["submission_id"] == leak_id and leak["team"] == "leaker"
    assert leak["evidence"]["median_ade_m"] < 1e-5 and leak["evidence"]["fraction_within_1cm"] == 1.0
    assert len(leak["evidence"]["closest_tokens"]) == 5 and "q25" in leak["evidence"]["quantiles_m"]

    (copy,) = by_kind["near_duplicate"]
    assert (copy["submission_id"], copy["other_submission_id"]) == (copy_id, original_id)
    assert copy["evidence"]["fraction_within_1cm"] == 1.0 and copy["evidence"]["same_sha256"] is False
    assert copy["evidence"]["other_team"] == "honest"

    (probe,) = by_kind["probing"]
    assert probe["team"] == "prober" and probe["evidence"]["submissions"] == probes
    counts = {tuple(pair["submissions"]): pair["differing_tokens"] for pair in probe["evidence"]["pairs"]}
    assert counts[(probes[0], probes[1])] == 1 and counts[(probes[0], probes[3])] == 3
    # The prober's own entries are not copies of each other for the cross-team check.
    assert all(flag["team"] != "prober" for flag in by_kind["near_duplicate"])

    # Teams never see flags: the admin routes refuse a team token, and a team's view carries none.
    team_headers = {"Authorization": f"Bearer {copier_token}"}
    assert world.client.get("/api/v1/admin/integrity", headers=team_headers).status_code in (401, 403)
    seen = world.client.get(f"/api/v1/submissions/{copy_id}", headers=team_headers).json()
    assert "integrity" not in str(seen) and "near_duplicate" not in str(seen)
    # A flag acts on nothing: the entries stay as they were until an organiser decides.
    with transaction(world.factory) as session:
        assert not any(
            session.get(Submission, i).disqualified or session.get(Submission, i).admin_hidden  # type: ignore[union-attr]
            for i in (leak_id, copy_id, *probes)
        )


def test_a_new_check_replaces_the_split_s_flags_and_is_in_the_audit_log(world: World) -> None:
    human = _baseline("human")
    leaker, _ = add_team(world.factory, "leaker")
    _submit(world, leaker, human, "oracle")
    assert len(_check(world)["flags"]) == 1
    first = _check(world)  # a second check: one check per split remains
    assert len(first["flags"]) == 1
    audit = world.client.get("/api/v1/admin/audit", headers=world.admin_headers()).json()
    assert [entry["action"] for entry in audit].count("integrity_check") == 2


def test_an_unknown_split_is_a_404(world: World) -> None:
    response = world.client.post(
        "/api/v1/admin/integrity/checks", json={"split": "nope"}, headers=world.admin_headers()
    )
    assert response.status_code == 404 and "nope" in response.text


def test_the_console_page_states_the_thresholds_and_holds_no_data(world: World) -> None:
    page = world.client.get("/admin/integrity")
    assert page.status_code == 200
    assert f"under {LEAK_MEDIAN_ADE_M:g} m" in page.text and "agree within 1 cm" in page.text
    assert "integrity.js" in page.text and "console.js" in page.text


def test_the_command_line_checks_a_split_and_prints_each_flag(
    world: World, monkeypatch: pytest.MonkeyPatch
) -> None:
    leaker, _ = add_team(world.factory, "leaker")
    leak_id = _submit(world, leaker, _baseline("human"), "oracle")
    monkeypatch.setenv("DATA_DIR", str(world.settings.data_dir))
    monkeypatch.setenv("DATABASE_URL", world.settings.database_url)
    get_settings.cache_clear()
    app = typer.Typer()
    register(app)
    with transaction(world.factory) as session:
        split = phase_row(session, world.phase).split.name
    try:
        result = CliRunner().invoke(app, ["admin", "check-integrity", split])
    finally:
        get_settings.cache_clear()
    assert result.exit_code == 0, result.output
    (line,) = result.stdout.splitlines()
    flag = json.loads(line)
    assert (flag["kind"], flag["submission_id"]) == ("leaked_log", leak_id)
    assert "1 entry read; 1 flag" in result.stderr


def test_copies_and_probes_are_found_in_any_seed_and_the_evidence_names_the_seeds(world: World) -> None:
    human = _baseline("human")
    honest, _ = add_team(world.factory, "honest")
    original = _noisy(human, 0.4, 1)
    original_id = _submit(world, honest, (_noisy(human, 0.6, 4), original), "original")
    copier, _ = add_team(world.factory, "copier")
    # The copy hides in the copier's seed 2, behind two seeds of its own.
    copy_id = _submit(world, copier, (_noisy(human, 0.5, 5), _noisy(human, 0.7, 6), original), "copy")
    prober, _ = add_team(world.factory, "prober")
    base, cover = _noisy(human, 0.5, 3), _noisy(human, 0.8, 8)
    tokens = sorted(base)
    probes = []
    for step in range(4):  # seed 0 the same cover each time; the probes move one more token in seed 1
        changed = dict(base) | {tokens[i]: base[tokens[i]] + 2.0 for i in range(step)}
        probes.append(_submit(world, prober, (cover, changed), f"probe {step}"))

    by_kind: dict[str, list[dict]] = {}
    for flag in _check(world)["flags"]:
        by_kind.setdefault(flag["kind"], []).append(flag)
    (copy,) = by_kind["near_duplicate"]
    assert (copy["submission_id"], copy["other_submission_id"]) == (copy_id, original_id)
    assert copy["evidence"]["seeds"] == {"this": 2, "other": 1} and copy["evidence"]["seeds_compared"] == 6
    assert copy["evidence"]["matching_seed_pairs"] == [{"this": 2, "other": 1}]
    assert copy["evidence"]["fraction_within_1cm"] == 1.0
    assert "its seed 2 and their seed 1" in copy["summary"]
    (probe,) = by_kind["probing"]
    assert probe["team"] == "prober" and probe["evidence"]["submissions"] == probes
    pairs = {tuple(pair["submissions"]): pair for pair in probe["evidence"]["pairs"]}
    assert pairs[(probes[0], probes[3])]["seeds"] == [1, 1]
    assert pairs[(probes[0], probes[3])]["differing_tokens"] == 3


def _scored(world: World, submission_id: int, finished_ago: timedelta = timedelta(0)) -> None:
    """Mark a stored entry scored, as its run's last chunk does (the checks read only its trajectories)."""
    with transaction(world.factory) as session:
        submission = session.get(Submission, submission_id)
        assert submission is not None
        submission.status, submission.finished_at = Status.scored, utc_now() - finished_ago


def test_a_scored_run_is_followed_by_a_check_once_and_a_failed_check_is_logged_not_raised(
    world: World, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    leaker, _ = add_team(world.factory, "leaker")
    leak_id = _submit(world, leaker, (_noisy(_baseline("human"), 0.5, 9), _baseline("human")), "oracle")
    # Not scored yet (queued): nothing to check.
    assert check_integrity_after_run(world.factory, world.settings, leak_id) is None
    _scored(world, leak_id, finished_ago=2 * AFTER_COMMIT)
    first = check_integrity_after_run(world.factory, world.settings, leak_id)
    assert first is not None
    with transaction(world.factory) as session:
        (check,) = integrity_report(session)["checks"]
    assert check["id"] == first and check["finished_at"] is not None
    (flag,) = check["flags"]
    assert (flag["kind"], flag["submission_id"], flag["evidence"]["seed"]) == ("leaked_log", leak_id, 1)
    # Delivered again: the check that read this run is done, so nothing runs twice.
    assert check_integrity_after_run(world.factory, world.settings, leak_id) is None
    # A baseline's run asks for nothing; no organiser's action is recorded for the automatic checks.
    with transaction(world.factory) as session:
        baseline = session.get(Submission, leak_id)
        assert baseline is not None
        baseline.is_baseline = True
    assert check_integrity_after_run(world.factory, world.settings, leak_id) is None
    audit = world.client.get("/api/v1/admin/audit", headers=world.admin_headers()).json()
    assert "integrity_check" not in [entry["action"] for entry in audit]

    # A check that fails records why for the console and logs it; the caller (the worker's task) goes on.
    other, _ = add_team(world.factory, "other")
    other_id = _submit(world, other, _noisy(_baseline("human"), 0.5, 10), "other")
    _scored(world, other_id)

    def broken(*_: object) -> None:
        raise RuntimeError("scenes unreadable")

    monkeypatch.setattr(integrity, "human_futures", broken)
    with caplog.at_level(logging.ERROR, logger="server.services.integrity"):
        failed = check_integrity_after_run(world.factory, world.settings, other_id)
    assert failed is not None and "scenes unreadable" in caplog.text
    with transaction(world.factory) as session:
        checks = {c["id"]: c for c in integrity_report(session)["checks"]}
    assert checks[failed]["error"] == "RuntimeError: scenes unreadable"
    assert checks[first]["flags"]  # the last good flags stay until a check succeeds


def test_of_two_overlapping_checks_the_newer_one_s_flags_remain(world: World) -> None:
    leaker, _ = add_team(world.factory, "leaker")
    _submit(world, leaker, _baseline("human"), "oracle")
    with transaction(world.factory) as session:
        split = phase_row(session, world.phase).split
        older = integrity.start_check(session, None, split).id
        newer = integrity.start_check(session, None, split).id
    integrity.run_check(world.factory, world.settings, newer)
    integrity.run_check(world.factory, world.settings, older)  # finishes last: it gives way
    with transaction(world.factory) as session:
        assert [check.id for check in session.query(IntegrityCheck)] == [newer]
        (check,) = integrity_report(session)["checks"]
    assert check["id"] == newer and len(check["flags"]) == 1


def test_a_check_that_finds_chunks_waiting_goes_behind_them_once(
    world: World, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker's task: with a chunk queued it sends itself again, marked, and checks nothing; marked, or with
    no chunk waiting, it checks (scoring goes first, and a check is never sent back twice)."""
    from worker import tasks

    team, _ = add_team(world.factory, "team")
    submission_id = _submit(world, team, _noisy(_baseline("human"), 0.5, 12), "honest")
    _scored(world, submission_id, finished_ago=2 * AFTER_COMMIT)
    sent: list[tuple[int, bool]] = []
    monkeypatch.setattr(tasks, "get_settings", lambda: world.settings)
    monkeypatch.setattr(tasks, "_sessions", lambda _: world.factory)
    monkeypatch.setattr(
        tasks, "_send_integrity_check", lambda *args, **kwargs: sent.append((*args, *kwargs.values()))
    )
    with transaction(world.factory) as session:
        chunk = ScoringChunk(submission_id=submission_id, run=1, tokens=["t"], state=ChunkState.queued)
        session.add(chunk)
        session.flush()
        chunk_id = chunk.id

    def checks() -> int:
        with transaction(world.factory) as session:
            return len(integrity_report(session)["checks"])

    assert "behind the waiting chunks" in tasks.check_integrity(submission_id)
    assert sent == [(submission_id, True)] and checks() == 0
    assert "integrity check" in tasks.check_integrity(submission_id, True) and checks() == 1
    with transaction(world.factory) as session:
        session.get(ScoringChunk, chunk_id).state = ChunkState.done  # type: ignore[union-attr]
    _scored(world, submission_id)  # a newer run: its check is due again
    assert "behind" not in tasks.check_integrity(submission_id) and sent == [(submission_id, True)]
    assert checks() == 1  # the newer check replaced the older one
