"""Scoring tasks: a submission fans out into chunk tasks, and the chunk that writes the last rows aggregates.

`score_submission` claims the submission (status running, with a lease), checks its stored file and
sends one `score_chunk` per slice of the tokens not scored yet. Each chunk scores its tokens under every
metric version and seed and upserts the rows; in the same transaction, under the submission's row lock,
it marks the run scored when every expected row is there. The SQL row count is the barrier a chord would
be: a chord needs a result backend and, on a broker without native chord support (the embedded SQLite
one), a `chord_unlock` task polling it every second; this works the same on every broker, and a lost or
repeated chunk cannot produce a wrong count (rows are keyed by submission, version, seed and token).

`reap_leases` (beat) re-queues runs whose lease ran out without a chunk being written, and fails them
(refunded) after `max_attempts` claims. Database and broker outages are retried; every other error
fails the run with a message the team may read, and the worker goes on with the next task.
"""

from __future__ import annotations

import hashlib
import os
import traceback
from collections.abc import Callable, Sequence
from datetime import timedelta
from functools import lru_cache
from pathlib import Path
from time import perf_counter
from typing import Any

import kombu.exceptions
import sqlalchemy.exc
from celery import Task
from celery.exceptions import SoftTimeLimitExceeded
from celery.signals import worker_ready
from celery.utils.log import get_task_logger
from sqlalchemy.orm import Session, sessionmaker

from scorer.blas import engine_provenance, kernel_warning
from scorer.evaluate import TokenResult, score_tokens
from scorer.submission import Submission as Predictions
from scorer.submission import SubmissionError, load_submission, validate_submission
from server.db import make_engine, make_session_factory, transaction
from server.models import FailureKind, Submission, utc_now
from server.queue import SCORE_TASK, prune_embedded_broker
from server.services.errors import NotFound
from server.services.scoring import (
    ScoringJob,
    claim_submission,
    completed_tokens,
    expired_leases,
    finish_if_complete,
    load_job,
    mark_failed,
    requeue,
    stale_queued,
    write_chunk_results,
)
from server.settings import get_settings
from worker.app import CHUNK_TASK, REAP_TASK, app

log = get_task_logger(__name__)

# Only these are worth retrying: the next attempt may find the database or the broker back.
INFRASTRUCTURE_ERRORS = (sqlalchemy.exc.OperationalError, kombu.exceptions.OperationalError)
RETRY: dict[str, Any] = {
    "autoretry_for": INFRASTRUCTURE_ERRORS,
    "retry_backoff": 2,
    "retry_backoff_max": 60,
    "max_retries": 5,
}
ENGINE_FAILURE = "the scoring engine failed on this submission (not a problem of the file)"
MAX_LISTED_PROBLEMS = 5


class Rejected(Exception):
    """A run that cannot go on: `message` is shown to the team, `detail` only to admins."""

    def __init__(self, kind: FailureKind, message: str, detail: str | None = None) -> None:
        super().__init__(message)
        self.kind, self.message, self.detail = kind, message, detail


@worker_ready.connect
def _warn_about_kernels(**_: object) -> None:
    warning = kernel_warning()
    if warning is not None:
        log.warning("%s (results record their kernels: %s)", warning, engine_provenance())


@lru_cache(maxsize=2)
def _sessions(database_url: str) -> sessionmaker[Session]:
    """Return this process's session factory (created after the fork, in the pool process)."""
    return make_session_factory(make_engine(database_url))


def _worker_name(task: Task) -> str:
    return f"{task.request.hostname or 'worker'}/{os.getpid()}"


def _chunks(tokens: Sequence[str], size: int) -> list[list[str]]:
    return [list(tokens[start : start + size]) for start in range(0, len(tokens), size)]


def _job(session: Session, submission_id: int, storage_dir: Path) -> ScoringJob:
    """Return the run's scoring job; raise Rejected when the stored file is gone."""
    try:
        return load_job(session, submission_id, storage_dir)
    except FileNotFoundError as error:
        raise Rejected(
            FailureKind.infrastructure, "the stored copy of this file is missing", str(error)
        ) from None


def _unscored(
    sessions: sessionmaker[Session],
    submission_id: int,
    run: int,
    tokens: Sequence[str] | None,
    storage_dir: Path,
) -> tuple[ScoringJob, list[str]] | None:
    """Return the run's job and which of `tokens` (None: all the split's) lack rows; None if the run was dropped."""
    with sessions() as session:
        done = completed_tokens(session, submission_id, run)
        if done is None:
            return None
        job = _job(session, submission_id, storage_dir)
    return job, [token for token in (job.tokens if tokens is None else tokens) if token not in done]


def _predictions(job: ScoringJob) -> Predictions:
    """Return the stored file read again, or raise Rejected when it is damaged or no longer fits the split."""
    if hashlib.sha256(job.data).hexdigest() != job.sha256:
        raise Rejected(
            FailureKind.infrastructure,
            "the stored copy of this file is damaged (its sha256 differs from the upload)",
            f"stored bytes of submission {job.submission_id} do not hash to {job.sha256}",
        )
    try:
        predictions = load_submission(job.data, job.filename)
    except SubmissionError as error:
        listed = "; ".join(str(problem) for problem in error.problems[:MAX_LISTED_PROBLEMS])
        raise Rejected(FailureKind.submission, f"the file cannot be read: {listed}") from None
    problems = validate_submission(predictions, job.tokens)
    if problems:
        # The file was checked against the split at upload: the split's tokens changed since.
        raise Rejected(
            FailureKind.infrastructure,
            f"split {job.split_name} changed after the upload; the file no longer matches it",
            "; ".join(str(problem) for problem in problems[:MAX_LISTED_PROBLEMS]),
        )
    return predictions


def _guarded(submission_id: int, run: int, work: Callable[[], str]) -> str:
    """Run `work`; any error but a database or broker outage fails the run (team-safe text), not the task."""
    try:
        return work()
    except INFRASTRUCTURE_ERRORS:
        raise
    except Rejected as rejection:
        kind, message, detail = rejection.kind, rejection.message, rejection.detail
    except SoftTimeLimitExceeded:
        limit = app.conf.task_soft_time_limit
        kind, message, detail = (
            FailureKind.infrastructure,
            f"scoring a chunk took longer than the time limit of {limit:.0f} s",
            traceback.format_exc(),
        )
    except Exception:
        log.exception("submission %s run %s: scoring failed", submission_id, run)
        # Engine errors may quote hidden scenes: the team sees a summary, admins the traceback.
        kind, message, detail = FailureKind.infrastructure, ENGINE_FAILURE, traceback.format_exc()
    settings = get_settings()
    with transaction(_sessions(settings.database_url)) as session:
        mark_failed(session, submission_id, run, kind, message, detail)
    log.warning("submission %s run %s failed (%s): %s", submission_id, run, kind, message)
    return "failed"


@app.task(name=SCORE_TASK, bind=True, **RETRY)
def score_submission(self: Task, submission_id: int) -> str:
    """Claim a submission, check its stored file and send its unscored tokens out as chunk tasks."""
    settings = get_settings()
    sessions = _sessions(settings.database_url)
    try:
        with transaction(sessions) as session:
            run = claim_submission(session, submission_id, _worker_name(self), settings.lease_seconds)
    except NotFound:
        return f"submission {submission_id}: missing"
    if run is None:
        return f"submission {submission_id}: not active"

    def dispatch() -> str:
        unscored = _unscored(sessions, submission_id, run, None, settings.storage_dir)
        if unscored is None:
            return "dropped"
        job, missing = unscored
        predictions = _predictions(job)
        if not missing:  # every row was written before an interruption: only the aggregation is left
            with transaction(sessions) as session:
                finish_if_complete(
                    session, submission_id, run, engine_provenance(), settings.bootstrap_samples
                )
            return "finished"
        # A chunk holds about chunk_size (token, seed) pairs, whatever the number of seeds.
        size = max(1, settings.chunk_size // len(predictions.seeds))
        chunks = _chunks(missing, size)
        for chunk in chunks:
            score_chunk.delay(submission_id, run, chunk)
        return f"{len(chunks)} chunks"

    return f"submission {submission_id} run {run}: {_guarded(submission_id, run, dispatch)}"


@app.task(name=CHUNK_TASK, bind=True, **RETRY)
def score_chunk(self: Task, submission_id: int, run: int, tokens: list[str]) -> str:
    """Score some tokens of a run under every metric version and seed; aggregate if they were the last."""
    settings = get_settings()
    sessions = _sessions(settings.database_url)
    worker = _worker_name(self)

    def score() -> str:
        unscored = _unscored(sessions, submission_id, run, tokens, settings.storage_dir)
        if unscored is None:
            return "dropped"
        job, todo = unscored
        results: dict[str, tuple[list[TokenResult], float]] = {}
        if todo:  # a redelivered chunk whose rows are all written only checks for completion
            predictions = _predictions(job)
            for version in job.versions:
                started = perf_counter()
                rows = [
                    row
                    for seed, poses in enumerate(predictions.seeds)
                    for row in score_tokens(job.split_dir, settings.cache_dir, poses, version, todo, seed)
                ]
                results[version] = rows, perf_counter() - started
        with transaction(sessions) as session:
            for version, (rows, duration) in results.items():
                wanted = write_chunk_results(
                    session, submission_id, run, version, rows, worker, duration, settings.lease_seconds
                )
                if not wanted:
                    return "dropped"
            finished = finish_if_complete(
                session, submission_id, run, engine_provenance(), settings.bootstrap_samples
            )
        return "scored" if finished else f"{len(todo)} tokens"

    return f"submission {submission_id} run {run}: {_guarded(submission_id, run, score)}"


def _waiting_tasks() -> int:
    """Return how many tasks wait in the queue (not yet taken by any worker)."""
    queue = app.amqp.queues[app.conf.task_default_queue]
    with app.connection_for_read() as connection:
        _, count, _ = queue.bind(connection.default_channel).queue_declare()
    return int(count)


@app.task(name=REAP_TASK)
def reap_leases() -> dict[str, list[int]]:
    """Re-queue runs whose lease expired (failing those out of attempts) and re-send long-queued ones."""
    settings = get_settings()
    pruned = prune_embedded_broker(settings)
    if pruned:
        log.info("reaper: deleted %d delivered messages from the embedded broker", pruned)
    # Tasks still waiting in the queue may be the chunks of an expired lease that are merely late behind
    # other work: only an idle queue proves a run lost. Redis hands lost messages back by itself; the
    # embedded broker cannot, so this is how its runs recover.
    if _waiting_tasks():
        return {"postponed": []}
    now = utc_now()
    failed, resend = [], []
    with transaction(_sessions(settings.database_url)) as session:
        for submission_id in expired_leases(session, now):
            submission = session.get(Submission, submission_id)
            assert submission is not None
            if submission.attempts >= settings.max_attempts:
                message = (
                    f"scoring was interrupted {submission.attempts} times (a worker was lost or too slow)"
                )
                detail = f"lease expired at {submission.lease_expires_at}; last worker {submission.worker}"
                mark_failed(
                    session, submission_id, submission.run, FailureKind.infrastructure, message, detail
                )
                failed.append(submission_id)
            elif requeue(session, submission_id):
                resend.append(submission_id)
        resend += stale_queued(session, now - timedelta(seconds=2 * settings.reaper_interval))
    for submission_id in resend:
        score_submission.delay(submission_id)
    if failed or resend:
        log.warning("reaper: re-sent %s, failed %s", resend, failed)
    return {"resent": resend, "failed": failed}
