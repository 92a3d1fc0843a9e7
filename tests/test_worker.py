"""Real Celery worker processes (not eager mode) behind a real API process, on the embedded defaults (SQLite
database, SQLite broker) and on PostgreSQL + Redis: uploads are scored like the engine scores them, chunks
delivered twice never duplicate rows, the reaper recovers runs left without chunks, and broken inputs fail one
submission with a message while the worker goes on. A worker process reads a run's file once."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import math
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scratch import scratch_redis_queue
from server_testing import fresh_postgres_database
from sqlalchemy import select
from worker_testing import (
    Service,
    SplitFixture,
    direct_means,
    predictions,
    running_service,
    wait_for,
    write_submission,
)

from scorer.baselines import baseline_submission
from scorer.blas import engine_provenance
from scorer.evaluate import score_tokens
from scorer.submission import Submission as Predictions
from scorer.submission import SubmissionMetadata, dump_submission_json, load_submission
from scorer.versions import LOG_REPLAY_VERSIONS as VERSIONS
from server.db import transaction
from server.models import FailureKind, Result, SplitKind, Status, Submission, utc_now
from server.object_store import LocalStore
from server.queue import SCORE_TASK, celery_client, enqueue_submission
from server.runs import Rejected, ScoringJob, claim_submission
from server.runs._job import trajectories
from server.runs._plan import plan_chunks
from server.services.integrity import integrity_report
from server.services.leaderboard import subscore_columns
from server.services.splits import create_phase, register_split
from server.settings import get_settings
from server.storage import store_file, store_trajectories
from worker.app import CHUNK_TASK, INTEGRITY_TASK, SOFT_LIMIT_MARGIN_S, app
from worker.tasks import ENGINE_FAILURE

PROBES = Path(__file__).parent / "fixtures" / "epdms" / "probes"
REDIS_URL = os.environ.get("NAVSIM_LB_TEST_REDIS", "redis://127.0.0.1:6379/0")
MAX_ATTEMPTS = 3
NAVSIM_LB = str(Path(sys.executable).parent / "navsim-lb")


@pytest.fixture(
    scope="module", params=["embedded", pytest.param("postgresql+redis", marks=pytest.mark.services)]
)
def service(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, synthetic_split: SplitFixture
) -> Iterator[Service]:
    """API and worker (2 processes, reaper every second) on the embedded defaults or PostgreSQL + Redis."""
    root = tmp_path_factory.mktemp(f"service-{request.param}".replace("+", "-"))
    overrides = {"REAPER_INTERVAL": "1", "MAX_ATTEMPTS": str(MAX_ATTEMPTS)}
    if request.param == "embedded":
        with running_service(root, synthetic_split, overrides) as running:
            yield running
        return
    with fresh_postgres_database() as database_url, scratch_redis_queue(REDIS_URL, "navsim-lb-test") as queue:
        overrides |= {"DATABASE_URL": database_url, "BROKER_URL": REDIS_URL, "QUEUE_NAME": queue}
        with running_service(root, synthetic_split, overrides) as running:
            yield running


def test_only_scoring_a_chunk_has_a_soft_time_limit() -> None:
    """The planner writes to the broker; an exception raised inside such a write can leave the embedded broker's
    file locked, so only the hard limit (which kills the process) stops it. The reaper is no task at all."""
    limit = get_settings().task_time_limit
    chunk, planner = (app.tasks[name] for name in (CHUNK_TASK, SCORE_TASK))
    assert chunk.soft_time_limit == limit - SOFT_LIMIT_MARGIN_S
    assert planner.soft_time_limit is None
    assert app.conf.task_soft_time_limit is None
    assert not [name for name in app.tasks if "reap" in name]
    # The hard limit is the app's, for every task (Celery 5.4 leaves a task's own attribute unset); the
    # supervisor keeps it from what the consumer reports (worker.supervised).
    assert app.conf.task_time_limit == limit
    assert all(task.time_limit in (None, limit) for task in (chunk, planner))
    # A split's integrity check after a run may read every entry: twice as long, no soft limit.
    check = app.tasks[INTEGRITY_TASK]
    assert (check.time_limit, check.soft_time_limit) == (2 * limit, None)


def _chunks_ended(service: Service, submission_id: int) -> int:
    """Return how many chunk tasks of a submission the worker log shows as ended (whatever they did)."""
    pattern = rf"score_chunk\[[^\]]+\] succeeded in [^:]+: 'submission {submission_id} run"
    return len(re.findall(pattern, service.worker_log()))


def test_submit_cli_upload_is_scored_as_the_engine_scores_it(
    service: Service, synthetic_split: SplitFixture, tmp_path: Path
) -> None:
    entry = predictions(synthetic_split.directory, seeds=2, noise=0.2, method="two noisy seeds")
    path = write_submission(tmp_path / "entry.json", entry)
    done = subprocess.run(
        [NAVSIM_LB, "submit", str(path), "--server", service.url, "--token", service.team_token]
        + ["--phase", "test", "--method", "two noisy seeds", "--wait"],
        capture_output=True,
        check=False,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    submission_id = int(done.stdout.strip())
    assert "PDMS v1.1" in done.stderr and "EPDMS v2.2" in done.stderr  # the results table
    submission = service.submission(submission_id)
    assert (submission.status, submission.progress, submission.seed_count) == (Status.scored, 100, 2)
    assert service.rows(submission_id) == len(entry.seeds[0]) * 2 * len(VERSIONS)
    with service.factory() as session:  # the worker processes ran the kernels this process runs
        provenances = session.scalars(
            select(Result.engine_version).where(Result.submission_id == submission_id)
        )
        assert set(provenances) == {engine_provenance()}
    with service.client() as client:  # the team's entry on the leaderboard, whatever else it submitted
        assert (
            client.patch(f"/api/v1/submissions/{submission_id}", json={"selected": True}).status_code == 200
        )
    for version in VERSIONS:
        row = service.leaderboard_row(version, submission_id)
        expected = direct_means(synthetic_split, entry, version)
        assert row["seeds"]["count"] == 2
        # Equal up to summation order: the service averages seeds x tokens at once, the engine per seed.
        for column in ("score", *subscore_columns(version)):
            if math.isnan(
                expected[column]
            ):  # v2.2's EC where no token has the frame before: null on the board
                assert row[column] is None, (version, column)
                continue
            assert row[column] == pytest.approx(expected[column], rel=1e-12, abs=1e-12), (version, column)


def test_submit_cli_lists_every_problem_of_a_refused_file(
    service: Service, synthetic_split: SplitFixture, tmp_path: Path
) -> None:
    entry = predictions(synthetic_split.directory, seeds=1, noise=0.1, method="broken")
    missing, *_ = sorted(entry.seeds[0])
    del entry.seeds[0][missing]
    path = write_submission(tmp_path / "broken.json", entry)
    done = subprocess.run(
        [NAVSIM_LB, "submit", str(path), "--server", service.url, "--token", service.team_token],
        capture_output=True,
        check=False,
        text=True,
        timeout=120,
    )
    assert done.returncode != 0
    assert "HTTP 422" in done.stderr and missing in done.stderr and "missing" in done.stderr
    assert done.stdout == ""


def test_redelivered_chunks_never_duplicate_rows(service: Service, synthetic_split: SplitFixture) -> None:
    entry = predictions(synthetic_split.directory, seeds=2, noise=0.3, method="redelivered")
    submission_id = service.stored(entry)
    tokens = sorted(entry.seeds[0])
    with transaction(service.factory) as session:  # play the coordinator: claim and plan, then send by hand
        run = claim_submission(session, submission_id, "test-coordinator")
        submission = session.get(Submission, submission_id)
        first, rest = plan_chunks(session, submission, tokens, len(tokens) - 4)
    sender = celery_client(service.settings)
    rows_per_token = 2 * len(VERSIONS)

    sender.send_task(CHUNK_TASK, args=[submission_id, run, first])
    wait_for(lambda: service.rows(submission_id) == 8 * rows_per_token, "the first chunk's rows")
    # The same chunk again after its rows were written, and the rest delivered twice at the same time.
    for chunk in (first, rest, rest):
        sender.send_task(CHUNK_TASK, args=[submission_id, run, chunk])
    assert service.final(submission_id).status == Status.scored
    wait_for(lambda: _chunks_ended(service, submission_id) == 4, "all four chunk deliveries to end")
    assert service.rows(submission_id) == len(tokens) * rows_per_token
    # Every line a chunk logs names its submission and run as fields.
    assert f"submission={submission_id} run={run} " in service.worker_log()
    assert "raised unexpected" not in service.worker_log()
    assert service.result(submission_id, "v1.1")["score"] == pytest.approx(
        direct_means(synthetic_split, entry, "v1.1")["score"], rel=1e-12
    )


def test_chunks_with_their_contexts_store_the_v2_2_rows_of_the_whole_split(
    service: Service, tmp_path: Path
) -> None:
    """v2.2's EC pairs adjacent frames of a log, which chunks may hold apart: a run in chunks of 7 tokens, each
    scoring the earlier frames others hold beside its own, stores every row the engine gives the whole split at
    once (EC and its partner, the human filter's overrides), on the probe split's twins 0.5 s and 1 s apart."""
    name = f"probes-{tmp_path.name}"
    with transaction(service.factory) as session:
        split = register_split(session, name, PROBES)
        create_phase(
            session, name, split, opens_at=utc_now() - timedelta(days=30)
        )  # "test" stays the default
    path = PROBES / "submissions" / "swerve_left.json"
    entry = load_submission(path.read_bytes(), path.name)
    submission_id = service.stored(entry, phase=name)
    with transaction(service.factory) as session:
        run = claim_submission(session, submission_id, "test-coordinator")
        chunks = plan_chunks(session, session.get(Submission, submission_id), sorted(entry.seeds[0]), 7)
    sender = celery_client(service.settings)
    for chunk in chunks:
        sender.send_task(CHUNK_TASK, args=[submission_id, run, chunk])
    assert service.final(submission_id).status == Status.scored
    assert service.rows(submission_id) == len(entry.seeds[0]) * len(VERSIONS)

    whole = {r.token: r for r in score_tokens(PROBES, service.settings.cache_dir, entry.seeds[0], "v2.2")}
    with service.client() as client:
        response = client.get(f"/api/v1/submissions/{submission_id}/tokens", params={"version": "v2.2"})
    assert response.status_code == 200, response.text
    stored = {row["token"]: row for row in response.json()}
    assert stored.keys() == whole.keys()
    paired = 0
    for token, row in stored.items():
        expected = whole[token]
        assert row["valid"] == expected.valid, token
        metrics = {column: math.nan if value is None else value for column, value in row["metrics"].items()}
        assert metrics.keys() == expected.metrics.keys()
        for column, value in expected.metrics.items():
            assert value == metrics[column] or math.isnan(value) and math.isnan(metrics[column]), (
                token,
                column,
            )
        block = expected.detail["human_filter"]
        seen = {k: v for k, v in block.items() if k not in ("human", "agent_before")}
        if block["overridden"]:  # its own values where the filter set 1, not the human's scores
            seen["agent_before"] = {column: block["agent_before"][column] for column in block["overridden"]}
        assert row["detail"] == expected.detail | {"human_filter": seen}, token
        paired += "previous_token" in row["detail"].get("two_frame_extended_comfort", {})
    assert paired > 10  # the pairs the chunks cut apart were found


def test_reaper_requeues_a_run_left_without_chunks_and_fails_one_out_of_attempts(
    service: Service, synthetic_split: SplitFixture
) -> None:
    # As if a worker had claimed them and died before planning.
    entry = predictions(synthetic_split.directory, seeds=1, noise=0.4, method="lost once")
    lost = service.stored(entry, lost_claims=1)
    entry = predictions(synthetic_split.directory, seeds=1, noise=0.5, method="lost often")
    exhausted = service.stored(entry, lost_claims=MAX_ATTEMPTS)

    recovered = service.final(lost)
    assert (recovered.status, recovered.attempts) == (Status.scored, 2)
    failed = service.final(exhausted)
    assert (failed.status, failed.failure_kind, failed.charged) == (
        Status.failed,
        FailureKind.infrastructure,
        False,
    )
    assert f"interrupted {MAX_ATTEMPTS} times" in (failed.error or "")
    assert "refunded" in (failed.error or "")


def test_a_damaged_file_or_an_engine_error_fails_the_submission_and_the_worker_goes_on(
    service: Service, synthetic_split: SplitFixture, tmp_path: Path
) -> None:
    damaged = service.stored(predictions(synthetic_split.directory, seeds=1, noise=0.6, method="damaged"))
    stored = service.submission(damaged)
    (service.settings.storage_dir / stored.stored_name).write_bytes(b'{"format": "navsim-lb/submission"')
    enqueue_submission(damaged, service.settings)

    broken_split = tmp_path / "broken"
    shutil.copytree(synthetic_split.directory, broken_split)
    with transaction(service.factory) as session:
        split = register_split(session, f"broken-{tmp_path.name}", broken_split)
        # Opened before "test", so "test" stays the default phase of uploads.
        create_phase(session, f"broken-{tmp_path.name}", split, opens_at=utc_now() - timedelta(days=30))
    scene = next((broken_split / "scenes").iterdir())
    scene.unlink()
    scene.mkdir()  # the hidden scene cannot be read: an error inside the engine, not a token problem
    entry = predictions(synthetic_split.directory, seeds=1, noise=0.7, method="engine error")
    engine_error = service.stored(entry, phase=f"broken-{tmp_path.name}")
    enqueue_submission(engine_error, service.settings)

    failed = service.final(damaged)
    assert (failed.status, failed.failure_kind) == (Status.failed, FailureKind.infrastructure)
    assert "damaged" in (failed.error or "")
    failed = service.final(engine_error)
    assert (failed.status, failed.failure_kind) == (Status.failed, FailureKind.infrastructure)
    assert (failed.error or "").startswith(ENGINE_FAILURE)
    assert str(broken_split) not in (failed.error or "")  # hidden paths stay in the admins' detail
    assert "IsADirectoryError" in (failed.error_detail or "")
    with service.client() as client:  # the team sees the summary, never the detail
        seen = client.get(f"/api/v1/submissions/{engine_error}").json()
    assert seen["error"] == failed.error and "error_detail" not in seen

    assert service.worker.poll() is None
    after = predictions(synthetic_split.directory, seeds=1, noise=0.8, method="after the failures")
    assert service.final(service.upload(after, "after.json")).status == Status.scored


def test_a_process_reads_the_file_of_a_run_once_and_of_a_new_run_again(
    synthetic_split: SplitFixture, tmp_path: Path
) -> None:
    data = dump_submission_json(
        predictions(synthetic_split.directory, seeds=2, noise=0.3, method="read once")
    )
    store = LocalStore(tmp_path)
    sha256 = hashlib.sha256(data).hexdigest()
    job = ScoringJob(
        submission_id=1,
        run=1,
        filename="entry.json",
        stored_name=store_file(store, sha256, io.BytesIO(data)),
        sha256=sha256,
        split_name="synthetic",
        split_source=str(synthetic_split.directory),
        split_hash="",
        split_kind=SplitKind.log_replay,
        seed_count=2,
        versions=VERSIONS,
    )
    parsed = trajectories(job, store)
    assert len(parsed) == 2
    (tmp_path / job.stored_name).unlink()
    assert trajectories(job, store) is parsed  # the run's next chunk
    with pytest.raises(Rejected, match="missing"):
        trajectories(dataclasses.replace(job, run=2), store)
    # With the trajectories its upload's check parsed, a run reads those instead of parsing the file (which
    # must still be there, intact).
    store_file(store, sha256, io.BytesIO(data))
    store_trajectories(store, job.stored_name, sha256, parsed[:1])  # one seed: told apart from the file
    copied = trajectories(dataclasses.replace(job, run=3), store)
    assert len(copied) == 1 and list(copied[0]) == list(parsed[0])  # the copy's one seed, not the file's two
    assert all(np.array_equal(copied[0][t], parsed[0][t]) for t in parsed[0])


def test_a_scored_run_is_followed_by_its_split_s_integrity_check(
    service: Service, synthetic_split: SplitFixture
) -> None:
    """A worker's task checks the split once the run is scored: the log itself in seed 1 is flagged there."""
    honest = predictions(synthetic_split.directory, seeds=1, noise=0.5, method="honest seed")
    human = baseline_submission(synthetic_split.directory, "human", "log").seeds[0]
    entry = Predictions(SubmissionMetadata(method="the log in seed 1"), (honest.seeds[0], human))
    submission_id = service.upload(entry)
    assert service.final(submission_id).status == Status.scored

    def flagged() -> list[dict[str, Any]]:
        with service.factory() as session:
            return [
                flag
                for check in integrity_report(session)["checks"]
                for flag in check["flags"]
                if flag["submission_id"] == submission_id
                and flag["kind"] == "leaked_log"
                and check["finished_at"] is not None
            ]

    # Other flags may name it too: the module's other entries are the same team's near-copies (probing).
    (flag,) = wait_for(flagged, "the integrity check after the run")  # type: ignore[misc]
    assert flag["evidence"]["seed"] == 1
    assert re.search(
        rf"check_integrity\[[^\]]+\] succeeded in [^:]+: 'submission {submission_id}: integrity",
        service.worker_log(),
    )


def test_health_reports_database_broker_and_the_running_worker(service: Service) -> None:
    with service.client() as client:
        health = client.get("/api/v1/health").json()
    assert health["database"]["ok"] and health["broker"]["ok"], health
    # Redis answers a ping; on the embedded broker the worker's own heartbeats in the database answer.
    assert health["workers"]["ok"] is True and health["workers"]["count"] >= 1, health
    assert health["status"] == "ok", health
    if not service.settings.broker_url.startswith("redis"):
        assert "heartbeat" in health["workers"]["detail"], health
