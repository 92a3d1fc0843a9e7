"""A two-stage split on the server: registering a directory with `two_stage.json` makes a two-stage split, whose
runs are scored under NAVSIM's two-stage EPDMS (`server.runs.RUN_VERSIONS`), and whose uploads must be in a
two-stage form."""

from __future__ import annotations

import csv
import json
import math
import shutil
from dataclasses import replace
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from server_testing import REFERENCE_DIR, REFERENCE_SUBMISSIONS, World, add_team
from sqlalchemy import select
from two_stage_reference import EXCERPT as TWO_STAGE_DIR
from two_stage_reference import EXCERPT_STAGES as STAGES
from two_stage_reference import family_poses, family_submission

from scorer.submission import dump_two_stage_submission_json
from scorer.two_stage.split import MAPPING_FILE
from scorer.versions import DEFAULT_VERSION
from server.db import transaction
from server.models import Result, ScoringChunk, SplitKind, Submission, Summary, TokenResultRow, utc_now
from server.runs import (
    RUN_VERSIONS,
    ChunkStart,
    StartAction,
    chunk_inputs,
    claim_submission,
    mark_scored,
    plan_run,
    run_versions,
    score_chunk,
    start_chunk,
    write_chunk,
    write_chunk_results,
)
from server.runs._score import POISONED_TOKEN
from server.services.errors import Conflict
from server.services.splits import create_phase, register_split, split_tokens
from server.settings import Settings
from server.storage import read_trajectories

FULL_REFERENCE_PICKLE = Path(__file__).parent / "fixtures" / "epdms-two-stage" / "submissions" / "human.pkl"
PHASE = "navhard"


@pytest.fixture(scope="session")
def two_stage_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The excerpt's metric caches, built once for every test that scores it."""
    from scorer.evaluate import build_split_cache

    directory = tmp_path_factory.mktemp("two-stage-cache")
    assert build_split_cache(TWO_STAGE_DIR, directory, ["v2.2-two-stage"], workers=2) == {}
    return directory


@pytest.fixture
def server_settings(server_settings: Settings, two_stage_cache: Path) -> Settings:
    """The test database's settings, scoring from the excerpt's prebuilt caches."""
    return server_settings.model_copy(update={"cache_dir_option": two_stage_cache})


def add_two_stage_phase(world: World) -> None:
    """Register the excerpt as a two-stage split with an open phase `PHASE` ("test" stays the default)."""
    with transaction(world.factory) as session:
        split = register_split(session, PHASE, TWO_STAGE_DIR)
        create_phase(session, PHASE, split, opens_at=utc_now() - timedelta(days=30))


def post(world: World, data: bytes, name: str, phase: str = PHASE, team_token: str | None = None) -> Any:
    headers = {"Authorization": f"Bearer {team_token}"} if team_token else world.team_headers()
    return world.client.post(
        "/api/v1/submissions",
        headers=headers,
        files={"file": (name, data)},
        data={"phase": phase},
    )


def test_a_directory_with_a_stage_mapping_registers_as_a_two_stage_split(world: World) -> None:
    with transaction(world.factory) as session:
        two_stage = register_split(session, "navhard-excerpt", TWO_STAGE_DIR)
        one_stage = register_split(session, "reference-scenes", REFERENCE_DIR)
        assert (two_stage.kind, one_stage.kind) == (SplitKind.two_stage, SplitKind.log_replay)
        assert run_versions(two_stage) == ("v2.2-two-stage",)
        assert run_versions(one_stage) == ("v1.0", "v1.1", "v2.2")
        assert split_tokens(two_stage) == STAGES.stage_one_tokens + STAGES.stage_two_tokens
        assert two_stage.token_count == 36 == len(set(split_tokens(two_stage)))
    assert set(RUN_VERSIONS) == set(SplitKind)


def test_a_two_stage_split_is_refused_with_what_is_wrong(world: World, tmp_path: Path) -> None:
    broken = tmp_path / "split"
    shutil.copytree(TWO_STAGE_DIR / "scenes", broken / "scenes")
    document = json.loads((TWO_STAGE_DIR / MAPPING_FILE).read_text())
    document["reactive_all_mapping"][1][0] = "not-a-token"
    (broken / MAPPING_FILE).write_text(json.dumps(document))
    with transaction(world.factory) as session, pytest.raises(Conflict) as refused:
        register_split(session, "broken", broken)
    assert "no scene file for token(s) not-a-token" in refused.value.message
    assert str(tmp_path) not in refused.value.message  # the server's paths stay on the server
    with transaction(world.factory) as session, pytest.raises(Conflict, match="no public and private"):
        register_split(session, "halves", TWO_STAGE_DIR, public_tokens=list(STAGES.stage_one_tokens[:2]))


def test_a_two_stage_upload_is_accepted_with_every_seed_in_the_official_row_order(world: World) -> None:
    add_two_stage_phase(world)
    response = post(world, dump_two_stage_submission_json(family_submission("human", seeds=2)), "two.json")
    assert response.status_code == 202, response.text
    with world.session() as session:
        submission = session.get(Submission, response.json()["id"])
        assert submission is not None
        assert (submission.seed_count, submission.token_count) == (2, 36)
        stored = read_trajectories(world.settings.submission_store, submission.stored_name, submission.sha256)
    assert stored is not None and len(stored) == 2
    assert list(stored[1]) == [*STAGES.stage_one_tokens, *STAGES.stage_two_tokens]
    token = STAGES.stage_two_tokens[4]
    assert np.array_equal(stored[1][token], family_poses("human")[token] + [0.3, 0.0, 0.0])


def test_missing_and_extra_tokens_are_listed_per_stage_before_anything_is_queued(world: World) -> None:
    add_two_stage_phase(world)
    submission = family_submission("human")
    dropped = STAGES.stage_two_tokens[7]
    del submission.second_stage[0][dropped]
    submission.first_stage[0]["0123456789abcdef"] = submission.first_stage[0][STAGES.stage_one_tokens[0]]
    response = post(world, dump_two_stage_submission_json(submission), "two.json")
    assert response.status_code == 422
    problems = {(p["field"], p["token"], p["message"]) for p in response.json()["problems"]}
    assert problems == {
        ("first_stage_predictions", "0123456789abcdef", "token is not in the split"),
        ("second_stage_predictions", dropped, "token of the split is missing"),
    }
    # NAVSIM's v2 pickle, read without running it: the whole reference's tokens, beyond the excerpt's.
    pickled = post(world, FULL_REFERENCE_PICKLE.read_bytes(), "human.pkl")
    assert pickled.status_code == 422
    extra = {(p["field"], p["message"]) for p in pickled.json()["problems"]}
    # 74 stage-one and 370 stage-two tokens beyond the excerpt: the first 50 listed, the rest counted.
    assert extra == {
        ("first_stage_predictions", "token is not in the split"),
        (None, "394 more problem(s) not listed"),
    }
    assert world.queued == []


def test_an_upload_in_the_other_kinds_form_is_refused_saying_which_form_the_split_takes(world: World) -> None:
    add_two_stage_phase(world)
    one_stage = (REFERENCE_SUBMISSIONS / "human.json").read_bytes()
    refused = post(world, one_stage, "human.json")
    assert refused.status_code == 422
    assert "is a two-stage split: it takes a two-stage submission" in refused.json()["detail"]
    assert "the file is a one-stage submission" in refused.json()["detail"]
    two_stage = dump_two_stage_submission_json(family_submission("human"))
    refused = post(world, two_stage, "two.json", phase="test")
    assert refused.status_code == 422
    assert "is a one-stage split: it takes a one-stage submission" in refused.json()["detail"]
    assert world.queued == []


# A run through the server equals `navsim-lb score --version v2.2-two-stage`, bit for bit -------------------


def _run_in_process(world: World, submission_id: int, chunk_size: int, dies: int = 0) -> list[list[str]]:
    """Play the workers of a run in this process: plan it in chunks of `chunk_size`, let the process of the
    first `dies` chunks die once (they are split one token per chunk), score and write every chunk. Return
    each scored chunk's tokens and context."""
    run, pending = _claim_and_plan(world, submission_id, chunk_size)
    with transaction(world.factory) as session:
        for chunk_id in pending[:dies]:
            session.get(ScoringChunk, chunk_id).deaths = 1  # type: ignore[union-attr]
    scored: list[list[str]] = []
    while pending:
        chunk_id = pending.pop(0)
        with transaction(world.factory) as session:
            start = start_chunk(session, chunk_id, run, "w")
        if start.action == StartAction.split_up:
            pending += start.children
            continue
        assert start.action == StartAction.score
        _score_and_write(world, submission_id, run, start)
        scored.append([*start.tokens, "|", *start.context])
    return scored


def _claim_and_plan(world: World, submission_id: int, chunk_size: int) -> tuple[int, list[int]]:
    """Claim the submission's run as worker "w" and plan it in chunks of `chunk_size`: the run, its chunks."""
    with transaction(world.factory) as session:
        run = claim_submission(session, submission_id, "w")
        assert run is not None
        plan = plan_run(session, submission_id, run, chunk_size, "test-engine", 200)
    return run, list(plan.chunks)


def _score_and_write(
    world: World, submission_id: int, run: int, start: ChunkStart, process_death: str | None = None
) -> None:
    """Score a started chunk as a worker does and write its rows; with `process_death`, as a worker does whose
    isolated process died so."""
    with world.session() as session:
        inputs = chunk_inputs(session, submission_id, run, start)
    assert inputs is not None
    inputs = replace(inputs, process_death=process_death)
    chunk = score_chunk(inputs, world.settings.submission_store, world.settings.cache_dir)
    with transaction(world.factory) as session:
        write_chunk(session, inputs, chunk, "w", "test-engine", 200)


def _cli_results(world: World, data: bytes, seeds: int, tmp_path: Path) -> list[dict[str, dict[str, str]]]:
    """Return per seed the official CSV `navsim-lb score` writes of the file: token -> its row."""
    from typer.testing import CliRunner

    from navsim_lb.cli import app

    path = tmp_path / "two.json"
    path.write_bytes(data)
    out = tmp_path / "results.csv"
    command = ["score", str(TWO_STAGE_DIR), str(path), "--version", "v2.2-two-stage", "--out", str(out)]
    result = CliRunner().invoke(app, [*command, "--cache-dir", str(world.settings.cache_dir)])
    assert result.exit_code == 0, result.output
    paths = [out] if seeds == 1 else [out.with_name(f"results.seed{seed}.csv") for seed in range(seeds)]
    with_rows = []
    for csv_path in paths:
        with csv_path.open(newline="") as file:
            with_rows.append({row["token"]: row for row in csv.DictReader(file)})
    return with_rows


def _field(value: float | None) -> str:
    """Return a value as the official CSV writes it (NaN, null here, as an empty field)."""
    return "" if value is None or (isinstance(value, float) and math.isnan(value)) else repr(value)


@pytest.mark.slow
def test_a_run_through_the_server_equals_the_command_line_bit_for_bit(world: World, tmp_path: Path) -> None:
    """Two seeds, chunks of whole groups, one chunk's process dying (its tokens then scored one per chunk with
    their comfort partner as context): every token's columns, the three summary rows per seed, each group's
    equal those of `navsim-lb score` on the same file; seed 0 is the reference family's own submission, whose
    weights and group values are the official ones."""
    from two_stage_reference import official_summary, official_tokens

    from scorer.two_stage.aggregate import SCORE_COLUMNS
    from scorer.two_stage.result_csv import STAGE_COLUMNS, SUMMARY_TOKENS

    add_two_stage_phase(world)
    submission = family_submission("swerve_left_fast", seeds=2)
    data = dump_two_stage_submission_json(submission)
    response = post(world, data, "two.json")
    assert response.status_code == 202, response.text
    submission_id = response.json()["id"]
    chunks = _run_in_process(world, submission_id, chunk_size=30, dies=1)
    group = STAGES.groups[0].tokens  # type: ignore[index]
    assert [group[0], "|", group[1]] in chunks  # orig alone, prev (its EC partner) as context
    assert any(chunk[: len(STAGES.groups[1].tokens)] == list(STAGES.groups[1].tokens) for chunk in chunks)  # type: ignore[index]

    official = _cli_results(world, data, 2, tmp_path)
    lines, groups = official_tokens("swerve_left_fast"), official_summary("swerve_left_fast")["groups"][:3]
    with world.session() as session:
        assert session.get(Submission, submission_id).status == "scored"  # type: ignore[union-attr]
        rows = session.scalars(
            select(TokenResultRow).where(TokenResultRow.submission_id == submission_id)
        ).all()
        results = {
            r.seed: r for r in session.scalars(select(Result).where(Result.submission_id == submission_id))
        }
        summary = session.scalars(select(Summary).where(Summary.submission_id == submission_id)).one()
        assert len(rows) == 72 and set(results) == {0, 1}
        for row in rows:
            expected = official[row.seed][row.token]
            stage = row.detail["two_stage"]["stage"]
            suffix = "_stage_one" if stage == 1 else "_stage_two"
            for column in STAGE_COLUMNS:
                assert _field(getattr(row, column)) == expected[column + suffix], (row.token, column)
            assert _field(row.score) == expected["score"], row.token
            if row.seed == 0:
                assert row.detail["two_stage"]["weight"] == lines[row.token]["weight"], row.token
        for seed, result in results.items():
            stage_one, stage_two, combined = (official[seed][token] for token in SUMMARY_TOKENS)
            assert _field(result.score) == combined["score"]
            for column in STAGE_COLUMNS:
                assert _field(result.two_stage["stage_one"][column]) == stage_one[column + "_stage_one"]
                assert _field(result.two_stage["stage_two"][column]) == stage_two[column + "_stage_two"]
            assert result.two_stage["official"] is True and len(result.two_stage["groups"]) == 3
        values = [group["combined"]["score"] for group in results[0].two_stage["groups"]]
        assert values == [group["combined"] for group in groups]
        scores = [float(official[seed][SUMMARY_TOKENS[2]]["score"]) for seed in (0, 1)]
        assert summary.score == float(np.mean(scores)) and summary.score_max == max(scores)
        assert summary.two_stage["groups"] == 3 and summary.ci_low <= summary.score <= summary.ci_high
        assert set(summary.two_stage["stage_one"]) == set(SCORE_COLUMNS)


# The board and the submission's groups ----------------------------------------------------------------------


def _scored_from_official(world: World, family: str, team_token: str | None = None) -> int:
    """Upload a family's excerpt submission and score it from the official per-token values; return its id."""
    data = dump_two_stage_submission_json(family_submission(family))
    response = post(world, data, f"{family}.json", team_token=team_token)
    assert response.status_code == 202, response.text
    submission_id: int = response.json()["id"]
    _write_official_rows(world, submission_id, family)
    return submission_id


def _write_official_rows(world: World, submission_id: int, family: str) -> None:
    """Play a run of the submission whose chunks give the official per-token values of `family` (what a chunk
    writes of them), then aggregate it."""
    from two_stage_reference import aggregation_input

    from server.runs._two_stage import stage_rows

    excerpt = set(split_tokens_of_excerpt())
    tokens = [item for item in aggregation_input(family) if item.result.token in excerpt]
    order = [item.result.token for item in tokens]
    with transaction(world.factory) as session:
        run = claim_submission(session, submission_id, "w")
        assert run is not None
        rows = stage_rows({0: tokens}, {0: order})
        assert write_chunk_results(session, submission_id, run, "v2.2-two-stage", rows, "w", 1.0)
        assert mark_scored(session, submission_id, run, "test-engine", 200)


def split_tokens_of_excerpt() -> tuple[str, ...]:
    return STAGES.stage_one_tokens + STAGES.stage_two_tokens


def test_the_two_stage_board_ranks_by_the_combined_score_with_each_stage(world: World) -> None:
    from two_stage_reference import aggregation_input, official_summary, official_tokens

    from scorer.two_stage.aggregate import aggregate_two_stage

    add_two_stage_phase(world)
    _, beta = add_team(world.factory, "beta")
    ids = {
        "human": _scored_from_official(world, "human"),
        "swerve_left_fast": _scored_from_official(world, "swerve_left_fast", beta),
    }
    expected = {
        family: aggregate_two_stage(
            [
                item
                for item in aggregation_input(family)
                if item.result.token in set(split_tokens_of_excerpt())
            ],
            STAGES,
        )
        for family in ids
    }
    board = world.client.get("/api/v1/leaderboard", params={"phase": PHASE}).json()
    assert (board["version"], board["versions"], board["two_stage"]) == (
        "v2.2-two-stage",
        ["v2.2-two-stage"],
        True,
    )
    assert board["interval_over"] == "groups" and "run_pdm_score_from_submission.py" in board["official_code"]
    ranked = [row for row in board["rows"] if not row["baseline"]]
    assert [row["method"] for row in ranked] == sorted(ids, key=lambda family: -expected[family].score)
    for row in ranked:
        result = expected[row["method"]]
        assert row["score"] == result.score and row["stage_one_score"] == result.stage_one["score"]
        assert row["stage_two"]["lane_keeping"] == result.stage_two["lane_keeping"]
        assert row["groups"] == 3 and row["undefined_groups"] == 0 and row["official"] is True
        assert row["ci95"][0] <= row["score"] <= row["ci95"][1]
    by_stage = world.client.get("/api/v1/leaderboard", params={"phase": PHASE, "sort": "stage_two_score"})
    assert by_stage.status_code == 200
    refused = world.client.get("/api/v1/leaderboard", params={"phase": PHASE, "version": "v2.2"})
    assert refused.status_code == 404 and "scored under v2.2-two-stage" in refused.json()["detail"]
    one_stage = world.client.get("/api/v1/leaderboard").json()  # the default phase keeps its default version
    assert (one_stage["version"], one_stage["two_stage"]) == (DEFAULT_VERSION, False)

    groups = world.client.get(f"/api/v1/submissions/{ids['human']}/groups", headers=world.team_headers())
    assert groups.status_code == 200, groups.text
    [seed] = groups.json()["seeds"]
    official_groups, lines = official_summary("human")["groups"], official_tokens("human")
    assert [group["score"] for group in seed["groups"]] == [
        group["combined"] for group in official_groups[:3]
    ]
    first = seed["groups"][0]
    assert first["original_stage_one"] == official_groups[0]["stage_one_now"]
    assert first["original_stage_two"] == official_groups[0]["stage_two_now_weighted"]
    assert first["weights"]["previous"] == {
        token: lines[token]["weight"]
        for token in STAGES.groups[0].previous_tokens  # type: ignore[index]
    }
    state = world.client.get(f"/api/v1/submissions/{ids['human']}", headers=world.team_headers()).json()
    assert (
        state["results"]["v2.2-two-stage"]["all"]["stage_one_score"] == expected["human"].stage_one["score"]
    )
    page = world.client.get(f"/?phase={PHASE}")
    assert page.status_code == 200 and "Stage 1" in page.text and "resamples groups" in page.text


def test_a_two_stage_rescore_reports_the_rank_changes_of_the_combined_score(world: World) -> None:
    add_two_stage_phase(world)
    _, beta = add_team(world.factory, "beta")
    alpha_id = _scored_from_official(world, "human")
    beta_id = _scored_from_official(world, "swerve_left_fast", beta)
    started = world.client.post("/api/v1/admin/rescore", json={"phase": PHASE}, headers=world.admin_headers())
    assert started.status_code == 202 and started.json()["queued"] == 2
    # The new run swaps the two entries' results.
    _write_official_rows(world, alpha_id, "swerve_left_fast")
    _write_official_rows(world, beta_id, "human")
    report = world.client.get(started.json()["report"], headers=world.admin_headers()).json()
    assert (report["version"], report["before_version"], report["complete"]) == ("v2.2-two-stage",) * 2 + (
        True,
    )
    moved = {m["team"]: (m["rank_before"], m["rank_after"]) for m in report["moved"]}
    assert moved["alpha"] == moved["beta"][::-1] and set(moved["alpha"]) == {1, 2}
    assert report["kendall_tau"] == -1.0
    exported = world.client.get(
        "/api/v1/admin/export", params={"phase": PHASE, "format": "json"}, headers=world.admin_headers()
    ).json()
    assert exported["version"] == "v2.2-two-stage"
    assert {row["submission_id"] for row in exported["rows"]} >= {alpha_id, beta_id}
    assert all("stage_two_score" in row for row in exported["rows"])


def test_a_token_that_killed_its_workers_is_written_failed_in_its_place_of_the_submission(
    world: World,
) -> None:
    """A group's chunk died: split one token per chunk, each scored isolated; a token whose isolated process
    died has a failed row that keeps its stage and its row in the submission (what the aggregation orders rows
    by), its points unknown."""
    add_two_stage_phase(world)
    response = post(world, dump_two_stage_submission_json(family_submission("human")), "two.json")
    submission_id = response.json()["id"]
    run, [first, *_] = _claim_and_plan(world, submission_id, 12)
    with transaction(world.factory) as session:
        session.get(ScoringChunk, first).deaths = 1  # type: ignore[union-attr]
    with transaction(world.factory) as session:
        split_up = start_chunk(session, first, run, "w")
    assert split_up.action == StartAction.split_up
    assert split_up.tokens == STAGES.groups[0].tokens  # type: ignore[index]
    child = split_up.children[2]  # the group's first now2
    with transaction(world.factory) as session:
        start = start_chunk(session, child, run, "w")
    assert (start.action, start.isolated) == (StartAction.score, True)
    _score_and_write(world, submission_id, run, start, process_death="killed by SIGSEGV")
    with world.session() as session:
        [row] = session.scalars(
            select(TokenResultRow).where(TokenResultRow.submission_id == submission_id)
        ).all()
    token = STAGES.groups[0].pairs[0][0]  # type: ignore[index]
    assert (row.token, row.valid, row.error) == (token, False, POISONED_TOKEN)
    submitted = [*STAGES.stage_one_tokens, *STAGES.stage_two_tokens]
    assert row.detail["two_stage"] == {
        "stage": 2,
        "row": submitted.index(token),
        "start_point": None,
        "endpoint": None,
    }
