"""Integrity checks for organisers on the reference scenes: a leaked log, a copy of another team's entry and a
team probing the hidden set are flagged with their evidence; honest entries are not; teams never see flags."""

from __future__ import annotations

import json
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
from server.models import Submission
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


def _submit(world: World, team_id: int, seed: Seed, method: str) -> int:
    """Store an entry of `team_id` as an upload would (its file and the trajectories its check parsed)."""
    with transaction(world.factory) as session:
        split = phase_row(session, world.phase).split
        predictions = Predictions(SubmissionMetadata(team_name=method, method=method), (seed,))
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
    assert f"under {LEAK_MEDIAN_ADE_M:g} m" in page.text and "within\n    1 cm" in page.text
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
