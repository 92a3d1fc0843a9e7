"""The services a worker calls: claim, chunk writes (idempotent, run-checked), progress and completion from the
chunk records, scored/failed, stalled runs."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from server_testing import (
    REFERENCE_DIR,
    World,
    add_phase,
    add_team,
    factory_for,
    fresh_postgres_database,
    phase_row,
    reference_tokens,
    score_run,
    team_row,
    token_results,
    uniform,
    upload_of,
)
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from scorer.evaluate import TokenResult
from scorer.versions import LOG_REPLAY_VERSIONS
from server.db import transaction
from server.migrate import upgrade
from server.models import ChunkState, Result, ScoringChunk, Status, Submission, TokenResultRow, utc_now
from server.object_store import LocalStore, ObjectStore
from server.runs import (
    cancel,
    claim_submission,
    mark_scored,
    reset_for_rerun,
    write_chunk_results,
)
from server.runs._finish import finish_if_complete
from server.runs._job import load_job
from server.runs._plan import plan_chunks
from server.runs._reaper import requeue, stale_queued, stalled_runs
from server.runs._rows import finish_chunk
from server.runs._run import completed_tokens
from server.services.errors import Conflict
from server.services.submissions import create_submission
from server.storage import read_file

TOKENS = reference_tokens()


def _new(factory: sessionmaker[Session], team_id: int, storage: ObjectStore, payload: bytes = b"x") -> int:
    with transaction(factory) as session:
        submission, _ = create_submission(
            session, team_row(session, team_id), phase_row(session, "test"), upload_of(payload), storage
        )
        return submission.id


def _rows(factory: sessionmaker[Session], submission_id: int) -> int:
    with factory() as session:
        return session.scalar(select(func.count()).where(TokenResultRow.submission_id == submission_id)) or 0


def _get(factory: sessionmaker[Session], submission_id: int) -> Submission:
    with factory() as session:
        submission = session.get(Submission, submission_id)
        assert submission is not None
        return submission


def test_job_names_the_stored_file_and_the_split(world: World) -> None:
    submission_id = _new(world.factory, world.team_id, world.settings.submission_store, b"file bytes")
    with world.session() as session:
        job = load_job(session, submission_id)
    assert read_file(world.settings.submission_store, job.stored_name) == b"file bytes"
    assert (job.run, Path(job.split_source), job.seed_count) == (1, REFERENCE_DIR, 1)
    assert job.versions == ("v1.0", "v1.1", "v2.2")


def _check_idempotent_chunks(factory: sessionmaker[Session], submission_id: int) -> None:
    with transaction(factory) as session:
        run = claim_submission(session, submission_id, "w1")
    assert run == 1 and _get(factory, submission_id).status == Status.running
    chunk = token_results(uniform(0.5, TOKENS[:20]))
    for _ in range(2):  # the broker redelivers the chunk
        with transaction(factory) as session:
            assert write_chunk_results(session, submission_id, run, "v1.1", chunk, "w1", 1.0)
    assert _rows(factory, submission_id) == 20
    changed = token_results(uniform(0.25, TOKENS[:20]))
    with transaction(factory) as session:
        write_chunk_results(session, submission_id, run, "v1.1", changed, "w2", 1.0)
    with factory() as session:
        scores = set(
            session.scalars(select(TokenResultRow.score).where(TokenResultRow.submission_id == submission_id))
        )
        workers = set(
            session.scalars(
                select(TokenResultRow.worker).where(TokenResultRow.submission_id == submission_id)
            )
        )
    assert (scores, workers, _rows(factory, submission_id)) == ({0.25}, {"w2"}, 20)


def test_redelivered_chunks_overwrite_instead_of_duplicating(
    new_submission: tuple[sessionmaker[Session], int],
) -> None:
    _check_idempotent_chunks(*new_submission)


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.services)])
def new_submission(
    request: pytest.FixtureRequest, tmp_path: Path
) -> Iterator[tuple[sessionmaker[Session], int]]:
    """A session factory and a new submission of team "alpha" in phase "test": on the test's own SQLite database,
    and on a fresh, migrated PostgreSQL database (dialect-specific writes)."""
    if request.param == "sqlite":
        world: World = request.getfixturevalue("world")
        yield world.factory, _new(world.factory, world.team_id, world.settings.submission_store)
        return
    with fresh_postgres_database() as url:
        upgrade(url)
        factory = factory_for(url)
        team_id, _ = add_team(factory, "alpha")
        add_phase(factory, "test")
        yield factory, _new(factory, team_id, LocalStore(tmp_path))
        factory.kw["bind"].dispose()


def _check_rows_read_back_as_written(factory: sessionmaker[Session], submission_id: int) -> None:
    """Every column of a row reads back as the chunk wrote it: values, nulls, details, errors, the time."""
    with transaction(factory) as session:
        run = claim_submission(session, submission_id, "w1")
    assert run is not None
    nan = float("nan")
    written = [
        TokenResult(
            TOKENS[0], 1, True, {"score": 0.75, "ego_progress": 0.5, "comfort": nan}, None, {"pair": "x"}
        ),
        TokenResult(TOKENS[1], None, True, {"score": 1.0, "ego_progress": 1.0}),
        TokenResult(TOKENS[2], 2, False, {"score": 0.9}, "no trajectory for this token"),
    ]
    now = utc_now() - timedelta(days=3, microseconds=17)
    with transaction(factory) as session:
        assert write_chunk_results(session, submission_id, run, "v2.2", written, "host/7", 0.3, now=now)
    with factory() as session:
        rows = {
            row.token: row
            for row in session.scalars(
                select(TokenResultRow).where(TokenResultRow.submission_id == submission_id)
            )
        }
    first, second, failed = (rows[token] for token in TOKENS[:3])
    assert (first.seed, first.valid, first.error, first.detail) == (1, True, None, {"pair": "x"})
    assert (first.score, first.ego_progress, first.comfort, first.lane_keeping) == (0.75, 0.5, None, None)
    assert (second.seed, second.detail, second.score, second.ego_progress) == (0, None, 1.0, 1.0)
    assert (failed.valid, failed.error, failed.score) == (False, "no trajectory for this token", None)
    assert {row.metric_version for row in rows.values()} == {"v2.2"}
    assert {(row.run, row.worker, row.scored_at) for row in rows.values()} == {(run, "host/7", now)}
    assert [row.duration_s for row in rows.values()] == pytest.approx([0.1] * 3)


def test_rows_read_back_as_written(new_submission: tuple[sessionmaker[Session], int]) -> None:
    _check_rows_read_back_as_written(*new_submission)


def _write_rows(session: Session, submission_id: int, tokens: list[str]) -> None:
    """Write every version's rows of `tokens` in run 1."""
    for version in LOG_REPLAY_VERSIONS:
        assert write_chunk_results(
            session, submission_id, 1, version, token_results(uniform(0.5, tokens)), "w1", 1
        )


def _write_chunk(factory: sessionmaker[Session], submission_id: int, chunk_id: int) -> bool:
    """Write a chunk's rows and finish it, as the worker holding it does; return whether the run is scored."""
    with transaction(factory) as session:
        chunk = session.get(ScoringChunk, chunk_id)
        assert chunk is not None
        _write_rows(session, submission_id, chunk.tokens)
        finish_chunk(session, chunk_id)
        return finish_if_complete(session, submission_id, 1, "e", 100)


def _check_finished_by_the_last_chunk(factory: sessionmaker[Session], submission_id: int) -> None:
    """Chunks of 16, then 16 and 8 tokens: the run is scored when the last live one finishes with every row."""
    with transaction(factory) as session:
        claim_submission(session, submission_id, "w1")
        (first,) = plan_chunks(session, session.get(Submission, submission_id), TOKENS[:16], 16)
    assert not _write_chunk(factory, submission_id, first)  # no chunk is live, but rows are missing
    assert _get(factory, submission_id).progress == 100 * 16 // 40
    with transaction(factory) as session:
        second, third = plan_chunks(session, session.get(Submission, submission_id), TOKENS[16:], 16)
        assert completed_tokens(session, submission_id, 1, among=TOKENS[12:20]) == set(TOKENS[12:16])
    assert not _write_chunk(factory, submission_id, third)  # 8 tokens
    assert _get(factory, submission_id).progress == 100 * 24 // 40
    with transaction(factory) as session:  # every row is there, but a chunk is still live
        _write_rows(session, submission_id, TOKENS)
        assert not finish_if_complete(session, submission_id, 1, "e", 100)
    assert _write_chunk(factory, submission_id, second)
    scored = _get(factory, submission_id)
    assert (scored.status, scored.progress) == (Status.scored, 100)
    assert _rows(factory, submission_id) == 40 * len(LOG_REPLAY_VERSIONS)


def test_the_last_chunk_finishes_the_run_and_finished_chunks_give_the_progress(
    new_submission: tuple[sessionmaker[Session], int],
) -> None:
    _check_finished_by_the_last_chunk(*new_submission)


def test_incomplete_runs_cannot_be_marked_scored(world: World) -> None:
    submission_id = _new(world.factory, world.team_id, world.settings.submission_store)
    with transaction(world.factory) as session:
        run = claim_submission(session, submission_id, "w1")
        write_chunk_results(session, submission_id, run, "v1.1", token_results(uniform(0.5)), "w1", 1.0)
    with (
        pytest.raises(Conflict, match=f"40 of {40 * len(LOG_REPLAY_VERSIONS)}"),
        transaction(world.factory) as session,
    ):
        mark_scored(session, submission_id, 1, "e", 100)
    assert _get(world.factory, submission_id).status == Status.running


def test_cancelled_or_rerun_submissions_drop_late_writes(world: World) -> None:
    submission_id = _new(world.factory, world.team_id, world.settings.submission_store)
    with transaction(world.factory) as session:
        run = claim_submission(session, submission_id, "w1")
        cancel(session, session.get(Submission, submission_id))
    with transaction(world.factory) as session:
        assert not write_chunk_results(
            session, submission_id, run, "v1.1", token_results(uniform(0.5)), "w1", 1, 60
        )
        assert claim_submission(session, submission_id, "w2") is None
    assert _rows(world.factory, submission_id) == 0
    with transaction(world.factory) as session:
        reset_for_rerun(session, session.get(Submission, submission_id))
    with transaction(world.factory) as session:
        assert not write_chunk_results(
            session, submission_id, run, "v1.1", token_results(uniform(0.5)), "w1", 1, 60
        )
        assert claim_submission(session, submission_id, "w2") == run + 1


def test_a_rerun_keeps_the_old_results_until_it_is_scored(world: World) -> None:
    submission_id = _new(world.factory, world.team_id, world.settings.submission_store)
    score_run(world.factory, submission_id, [uniform(0.4)])
    with transaction(world.factory) as session:
        reset_for_rerun(session, session.get(Submission, submission_id))
    board = world.client.get("/api/v1/leaderboard").json()["rows"]
    assert board[0]["score"] == pytest.approx(0.4)
    assert _get(world.factory, submission_id).progress == 0
    score_run(world.factory, submission_id, [uniform(0.6)])
    assert world.client.get("/api/v1/leaderboard").json()["rows"][0]["score"] == pytest.approx(0.6)
    with world.session() as session:
        results = session.scalars(select(Result).where(Result.submission_id == submission_id)).all()
    # one row per (version, subset, seed): every version on "all", with provenance
    assert sorted((r.metric_version, r.subset, r.seed) for r in results) == [
        ("v1.0", "all", 0),
        ("v1.1", "all", 0),
        ("v2.2", "all", 0),
    ]
    assert {(r.engine_version, r.workers, r.tokens) for r in results} == {("test-engine", "test-worker", 40)}
    assert results[0].duration_s == pytest.approx(3 * 0.5)  # three chunks (16, 16, 8 tokens) of 0.5 s each


def test_a_claimed_run_without_live_chunks_is_stalled_and_requeued(world: World) -> None:
    submission_id = _new(world.factory, world.team_id, world.settings.submission_store)
    with transaction(world.factory) as session:
        claim_submission(session, submission_id, "w1")
    with world.session() as session:
        assert stalled_runs(session, utc_now() - timedelta(seconds=30)) == []  # claimed a moment ago
        assert stalled_runs(session, utc_now() + timedelta(seconds=1)) == [submission_id]
    with transaction(world.factory) as session:
        submission = session.get(Submission, submission_id)
        plan_chunks(session, submission, TOKENS[:3], 2)
    with world.session() as session:  # a queued chunk is in flight: not stalled
        assert stalled_runs(session, utc_now() + timedelta(seconds=1)) == []
    with transaction(world.factory) as session:
        session.execute(update(ScoringChunk).values(state=ChunkState.done))
    with world.session() as session:
        assert stalled_runs(session, utc_now() + timedelta(seconds=1)) == [submission_id]
    with transaction(world.factory) as session:
        assert requeue(session, submission_id)
    assert _get(world.factory, submission_id).status == Status.queued


def test_submissions_queued_too_long_are_found(world: World) -> None:
    submission_id = _new(world.factory, world.team_id, world.settings.submission_store)
    with world.session() as session:
        assert stale_queued(session, utc_now() - timedelta(minutes=5)) == []
        assert stale_queued(session, utc_now() + timedelta(seconds=1)) == [submission_id]
    with transaction(world.factory) as session:
        claim_submission(session, submission_id, "w1")
    with world.session() as session:
        assert stale_queued(session, utc_now() + timedelta(seconds=1)) == []
