"""Scoring tasks: a submission fans out into chunk tasks, and the chunk that writes the last rows aggregates.

`score_submission` claims the submission (status running), then records one chunk per slice of the tokens
not scored yet (server.services.chunks) and sends them. Each chunk scores its
tokens under every metric version and seed, beating while it does, and upserts the rows; in the same
transaction, under the submission's row lock, it marks the run scored when no chunk of the run is left
and every expected row is there. The SQL records are the barrier a chord would be: a chord needs a result
backend and, on a broker without native chord support (the embedded SQLite one), a `chord_unlock` task
polling it every second; this works the same on every broker, and a lost or repeated chunk cannot produce
a wrong count (rows are keyed by submission, version, seed and token).

A process keeps the trajectories it read last (`_predictions`): every chunk of a run scores the same file. It
reads them from the copy the upload's check parsed (server.storage): parsing a navtest-size file again
(12,000 tokens x 3 seeds) costs as much as scoring a chunk.

`reap_lost_work` (beat) holds the broker to the SQL record: it re-sends the chunks of processes that
stopped beating (splitting, then failing, a token that kills its workers), what the broker lost, and runs
left with nothing in flight (failed, refunded, after `max_attempts` claims). Database and broker outages
are retried; every other error fails the run with a message the team may read, and the worker goes on.
"""

from __future__ import annotations

import hashlib
import os
import traceback
from collections.abc import Callable, Mapping, Sequence
from datetime import timedelta
from functools import lru_cache
from pathlib import Path
from time import monotonic, perf_counter, sleep
from typing import Any

import kombu.exceptions
import sqlalchemy.exc
from celery import Task
from celery.exceptions import SoftTimeLimitExceeded
from celery.signals import worker_ready
from celery.utils.log import get_task_logger
from sqlalchemy.orm import Session, sessionmaker

from scorer.blas import engine_provenance, kernel_warning
from scorer.evaluate import TokenResult, score_seeds
from scorer.geometry import FloatArray
from scorer.scene import scene_paths
from scorer.submission import SubmissionError, coverage_problems, load_submission
from server.db import make_engine, make_session_factory, transaction
from server.models import ChunkState, FailureKind, Submission, utc_now
from server.queue import SCORE_TASK, prune_embedded_broker, waiting_tasks
from server.services.chunks import (
    StartAction,
    dead_chunks,
    finish_chunk,
    forgotten_chunks,
    plan_chunks,
    resend_chunk,
    start_chunk,
)
from server.services.errors import NotFound
from server.services.scoring import (
    ScoringJob,
    add_admin_detail,
    claim_submission,
    completed_tokens,
    finish_if_complete,
    load_job,
    mark_failed,
    mark_requeued,
    requeue,
    stale_queued,
    stalled_runs,
    write_chunk_results,
)
from server.services.splits import split_tokens
from server.settings import get_settings
from server.storage import read_file, read_trajectories
from worker.app import CHUNK_TASK, REAP_TASK, app, chunk_soft_time_limit
from worker.heartbeat import beating

log = get_task_logger(__name__)

# Only these are worth retrying: the next attempt may find the database or the broker back.
DATABASE_OUTAGES = (sqlalchemy.exc.OperationalError, sqlalchemy.exc.InterfaceError)
INFRASTRUCTURE_ERRORS = (*DATABASE_OUTAGES, kombu.exceptions.OperationalError)
# Before a task holds anything: 2 + 4 + ... + 60 s, about six minutes of outage, without jitter.
RETRY: dict[str, Any] = {
    "autoretry_for": INFRASTRUCTURE_ERRORS,
    "retry_backoff": 2,
    "retry_backoff_max": 60,
    "retry_jitter": False,
    "max_retries": 10,
}
# A chunk's scored rows are in memory: their write waits out a database outage this long, in the task.
DATABASE_OUTAGE_S = 360.0
DATABASE_RETRY_MAX_S = 15.0
ENGINE_FAILURE = "the scoring engine failed on this submission (not a problem of the file)"
POISONED_TOKEN = (
    "scoring this token stopped the worker process twice (a crash or running out of memory); "
    "it was not scored and counts as a failed token"
)
MAX_LISTED_PROBLEMS = 5
# Parsed files a process keeps: the run it scores, and one more for the chunks of two runs interleaving.
PARSED_FILES_KEPT = 2


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


def _unscored(
    sessions: sessionmaker[Session], submission_id: int, run: int, tokens: Sequence[str]
) -> tuple[ScoringJob, list[str]] | None:
    """Return the run's job and which of `tokens` lack rows; None if the run is no longer wanted."""
    with sessions() as session:
        done = completed_tokens(session, submission_id, run, among=tokens)
        if done is None:
            return None
        job = load_job(session, submission_id)
    return job, [token for token in tokens if token not in done]


def _stored_file(job: ScoringJob, storage_dir: Path) -> bytes:
    """Return the stored bytes of the run's file, or raise Rejected when they are missing or damaged."""
    try:
        data = read_file(storage_dir, job.stored_name)
    except FileNotFoundError as error:
        raise Rejected(
            FailureKind.infrastructure, "the stored copy of this file is missing", str(error)
        ) from None
    if hashlib.sha256(data).hexdigest() != job.sha256:
        raise Rejected(
            FailureKind.infrastructure,
            "the stored copy of this file is damaged (its sha256 differs from the upload)",
            f"stored bytes of submission {job.submission_id} do not hash to {job.sha256}",
        )
    return data


@lru_cache(maxsize=PARSED_FILES_KEPT)
def _predictions(job: ScoringJob, storage_dir: Path) -> tuple[dict[str, FloatArray], ...]:
    """Return each seed's trajectories of the run, or raise Rejected when its stored file is missing, damaged or
    no longer fits the split. A run's file is checked and read once per process; an error is raised again each
    time.

    The trajectories come from the copy its upload's check parsed; without one (an upload stored before those
    copies, or a copy lost) the file is parsed again.
    """
    data = _stored_file(job, storage_dir)
    seeds = read_trajectories(storage_dir, job.stored_name, job.sha256)
    if seeds is None:
        try:
            seeds = load_submission(data, job.filename).seeds
        except SubmissionError as error:
            listed = "; ".join(str(problem) for problem in error.problems[:MAX_LISTED_PROBLEMS])
            raise Rejected(FailureKind.submission, f"the file cannot be read: {listed}") from None
    problems = coverage_problems([list(seed) for seed in seeds], scene_paths(job.split_dir))
    if problems:
        # The file was checked against the split at upload: the split's tokens changed since.
        raise Rejected(
            FailureKind.infrastructure,
            f"split {job.split_name} changed after the upload; the file no longer matches it",
            "; ".join(str(problem) for problem in problems[:MAX_LISTED_PROBLEMS]),
        )
    return seeds


def _through_database_outages(write: Callable[[], str]) -> str:
    """Run a database write, retrying while the database is unreachable (a chunk keeps its scored rows).

    Retrying the whole task instead would score again, and its chunk, held by this task, would not start.
    """
    deadline, delay = monotonic() + DATABASE_OUTAGE_S, 1.0
    while True:
        try:
            return write()
        except DATABASE_OUTAGES as error:
            if monotonic() > deadline:
                raise
            log.warning("database unreachable, writing again in %.0f s: %s", delay, error)
            sleep(delay)
            delay = min(2 * delay, DATABASE_RETRY_MAX_S)


def _guarded(submission_id: int, run: int, work: Callable[[], str]) -> str:
    """Run `work`; any error but a database or broker outage fails the run (team-safe text), not the task."""
    try:
        return work()
    except INFRASTRUCTURE_ERRORS:
        raise
    except Rejected as rejection:
        kind, message, detail = rejection.kind, rejection.message, rejection.detail
    except SoftTimeLimitExceeded:
        limit = chunk_soft_time_limit(get_settings())
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
    """Claim a submission and send its unscored tokens out as chunk tasks (or aggregate, if none is left)."""
    settings = get_settings()
    sessions = _sessions(settings.database_url)
    try:
        with transaction(sessions) as session:
            run = claim_submission(session, submission_id, _worker_name(self))
    except NotFound:
        return f"submission {submission_id}: missing"
    if run is None:
        return f"submission {submission_id}: not active"

    def dispatch() -> str:
        # A run claimed but never planned (this process died in between) is re-planned by the reaper.
        with transaction(sessions) as session:
            submission = session.get(Submission, submission_id)
            done = completed_tokens(session, submission_id, run)
            if submission is None or done is None:
                return "dropped"
            missing = [token for token in split_tokens(submission.split) if token not in done]
            if not missing:  # every row was written before an interruption: only the aggregation is left
                finish_if_complete(
                    session, submission_id, run, engine_provenance(), settings.bootstrap_samples
                )
                return "finished"
            # A chunk holds about chunk_size (token, seed) pairs, whatever the number of seeds.
            size = max(1, settings.chunk_size // submission.seed_count)
            chunks = plan_chunks(session, submission, missing, size)
        for chunk_id in chunks:  # a chunk recorded but never sent is re-sent by the reaper
            score_chunk.delay(submission_id, run, chunk_id)
        return f"{len(chunks)} chunks"

    return f"submission {submission_id} run {run}: {_guarded(submission_id, run, dispatch)}"


def _failed_rows(job: ScoringJob, tokens: Sequence[str]) -> dict[str, list[TokenResult]]:
    """Return failed rows for `tokens` under every version and seed of the job (a poisoned token)."""
    rows = [
        TokenResult(token, seed, valid=False, error=POISONED_TOKEN)
        for seed in range(job.seed_count)
        for token in tokens
    ]
    return dict.fromkeys(job.versions, rows)


@app.task(name=CHUNK_TASK, bind=True, **RETRY)
def score_chunk(self: Task, submission_id: int, run: int, chunk_id: int) -> str:
    """Score a chunk's tokens under every metric version and seed; aggregate if they were the last."""
    settings = get_settings()
    sessions = _sessions(settings.database_url)
    worker = _worker_name(self)
    with transaction(sessions) as session:
        start = start_chunk(session, chunk_id, run, worker)
    if start.action == StartAction.drop:
        return f"submission {submission_id} run {run}: chunk {chunk_id} dropped"
    if start.action == StartAction.split_up:
        for child in start.children:
            score_chunk.delay(submission_id, run, child)
        return f"submission {submission_id} run {run}: chunk {chunk_id} split into {len(start.children)}"

    def score() -> str:
        unscored = _unscored(sessions, submission_id, run, start.tokens)
        if unscored is None:
            return "dropped"
        job, todo = unscored
        poisoned = start.action == StartAction.poisoned and bool(todo)
        timed: dict[str, tuple[list[TokenResult], float]] = {}
        if poisoned:
            timed = {version: (rows, 0.0) for version, rows in _failed_rows(job, todo).items()}
        elif todo:  # a chunk whose rows were all written by an earlier holder only checks for completion
            predictions = _predictions(job, settings.storage_dir)
            # Tokens written already still pair with the rest for EC, as the chunk's context does.
            context = [*start.context, *(token for token in start.tokens if token not in todo)]
            with beating(sessions, chunk_id, worker):
                started = perf_counter()
                # Every seed and version at once: a token's caches read once, each trajectory simulated once.
                seeds: dict[int | None, Mapping[str, object]] = dict(enumerate(predictions))
                rows = score_seeds(
                    job.split_dir, settings.cache_dir, seeds, job.versions, todo, context=context
                )
                share = (perf_counter() - started) / len(job.versions)
                timed = {version: (version_rows, share) for version, version_rows in rows.items()}

        def write() -> str:
            with transaction(sessions) as session:
                for version, (rows, duration) in timed.items():
                    if not write_chunk_results(session, submission_id, run, version, rows, worker, duration):
                        return "dropped"
                finish_chunk(session, chunk_id, ChunkState.failed if poisoned else ChunkState.done)
                if poisoned:
                    detail = f"token {', '.join(todo)}: written as failed, {POISONED_TOKEN}"
                    add_admin_detail(session, submission_id, detail)
                finished = finish_if_complete(
                    session, submission_id, run, engine_provenance(), settings.bootstrap_samples
                )
            return "scored" if finished else f"{len(todo)} tokens"

        return _through_database_outages(write)

    return f"submission {submission_id} run {run}: {_guarded(submission_id, run, score)}"


@app.task(name=REAP_TASK)
def reap_lost_work() -> dict[str, list[int]]:
    """Re-send what died or what the broker lost, and fail what cannot finish (see the module docstring)."""
    settings = get_settings()
    sessions = _sessions(settings.database_url)
    now = utc_now()
    chunks: list[tuple[int, int, int]] = []
    submissions: list[int] = []
    failed: list[int] = []
    with transaction(sessions) as session:
        # A beat that stopped is proof on its own: its chunk is sent again whatever the queue holds.
        for chunk in dead_chunks(session, now):
            assert chunk.started_at is not None
            if (now - chunk.started_at).total_seconds() >= settings.task_time_limit:
                message = f"scoring was stopped at the hard time limit of {settings.task_time_limit:.0f} s"
                detail = f"chunk {chunk.id} of {len(chunk.tokens)} tokens, started {chunk.started_at} by {chunk.worker}"
                mark_failed(
                    session, chunk.submission_id, chunk.run, FailureKind.infrastructure, message, detail
                )
                failed.append(chunk.submission_id)
            else:
                chunks.append(
                    (chunk.submission_id, chunk.run, resend_chunk(session, chunk, died=True, now=now))
                )
    # What waits in SQL but not in an idle queue was lost by the broker, or is held by a worker that took
    # it a moment ago: after one reaper interval it is sent again (a duplicate drops).
    if not waiting_tasks(settings, declare=True):
        sent_before = now - timedelta(seconds=settings.reaper_interval)
        with transaction(sessions) as session:
            chunks.extend(
                (chunk.submission_id, chunk.run, resend_chunk(session, chunk, died=False, now=now))
                for chunk in forgotten_chunks(session, sent_before)
            )
            for submission_id in stalled_runs(session, sent_before):
                submission = session.get(Submission, submission_id)
                assert submission is not None
                if submission.attempts >= settings.max_attempts:
                    message = (
                        f"scoring was interrupted {submission.attempts} times (a worker was lost or too slow)"
                    )
                    detail = f"claimed at {submission.claimed_at}; last worker {submission.worker}"
                    mark_failed(
                        session, submission_id, submission.run, FailureKind.infrastructure, message, detail
                    )
                    failed.append(submission_id)
                elif requeue(session, submission_id):
                    submissions.append(submission_id)
            resent = stale_queued(session, sent_before)
            mark_requeued(session, resent, now)
            submissions += resent
    for submission_id, run, chunk_id in chunks:
        score_chunk.delay(submission_id, run, chunk_id)
    for submission_id in submissions:
        score_submission.delay(submission_id)
    if chunks or submissions or failed:
        log.warning("reaper: re-sent chunks %s and submissions %s, failed %s", chunks, submissions, failed)
    # Housekeeping last: the work above (failing a run past the hard limit above all) never waits on it.
    pruned = prune_embedded_broker(settings)
    if pruned:
        log.info("reaper: deleted %d delivered messages from the embedded broker", pruned)
    return {"chunks": [chunk_id for _, _, chunk_id in chunks], "submissions": submissions, "failed": failed}
