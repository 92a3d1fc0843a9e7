"""The Celery glue of a scoring run (its lifecycle lives in server.runs): tasks, limits, retries, signals.

`score_submission` claims a submission and plans its chunks, then sends them; `score_chunk` takes a chunk,
scores it while beating for it, and writes its rows, the chunk that writes the last rows aggregating. The SQL
records are the barrier a chord would be: a chord needs a result backend and, on a broker without native
chord support (the embedded SQLite one), a `chord_unlock` task polling it every second; this works the same
on every broker, and a lost or repeated chunk cannot produce a wrong count (rows are keyed by submission,
version, seed and token).

`reap_lost_work` (no task: the reaper's own process calls it, worker.reaper) sends again what server.runs'
reaper decides. Database and broker outages are retried; every other error fails the run with a message the
team may read, and the worker goes on.
"""

from __future__ import annotations

import os
import traceback
from collections.abc import Callable
from dataclasses import replace
from datetime import timedelta
from functools import lru_cache, partial
from time import monotonic, sleep
from typing import Any, TypeVar

import kombu.exceptions
import sqlalchemy.exc
from celery import Task
from celery.exceptions import SoftTimeLimitExceeded
from celery.signals import worker_ready
from celery.utils.log import get_task_logger
from sqlalchemy.orm import Session, sessionmaker

from scorer.blas import engine_provenance, kernel_warning
from server import runs
from server.db import make_engine, make_session_factory, transaction
from server.models import FailureKind, utc_now
from server.object_store import StoreUnavailable, connect
from server.queue import SCORE_TASK, prune_embedded_broker, waiting_tasks
from server.services.errors import NotFound
from server.settings import get_settings
from worker.app import CHUNK_TASK, INTEGRITY_TASK, app, chunk_soft_time_limit
from worker.heartbeat import beating
from worker.isolated import ProcessDeath, run_isolated

log = get_task_logger(__name__)
T = TypeVar("T")

# Only these are worth retrying: the next attempt may find the database, the broker or the object store back.
DATABASE_OUTAGES = (sqlalchemy.exc.OperationalError, sqlalchemy.exc.InterfaceError)
INFRASTRUCTURE_ERRORS = (*DATABASE_OUTAGES, kombu.exceptions.OperationalError, StoreUnavailable)
# Before a task holds anything: 2 + 4 + ... + 60 s, about six minutes of outage, without jitter.
RETRY: dict[str, Any] = {
    "autoretry_for": INFRASTRUCTURE_ERRORS,
    "retry_backoff": 2,
    "retry_backoff_max": 60,
    "retry_jitter": False,
    "max_retries": 10,
}
# A chunk's scored rows are in memory: their write waits out a database outage this long, in the task; a held
# chunk's reads wait out an object store's outage as long, beating (retrying the task would leave it held).
OUTAGE_S = 360.0
OUTAGE_RETRY_MAX_S = 15.0
ENGINE_FAILURE = "the scoring engine failed on this submission (not a problem of the file)"


@worker_ready.connect
def _warn_about_kernels(**_: object) -> None:
    warning = kernel_warning()
    if warning is not None:
        log.warning("%s (results record their kernels: %s)", warning, engine_provenance())


@worker_ready.connect
def _connect_to_the_store(**_: object) -> None:
    connect(get_settings().submission_store)  # the caches' store, if any, is the same one


@lru_cache(maxsize=2)
def _sessions(database_url: str) -> sessionmaker[Session]:
    """Return this process's session factory (made on first use, in the process that uses it)."""
    return make_session_factory(make_engine(database_url))


def _worker_name(task: Task) -> str:
    return f"{task.request.hostname or 'worker'}/{os.getpid()}"


def _through_outages(work: Callable[[], T], outages: tuple[type[Exception], ...], what: str) -> T:
    """Run `work` of a held chunk, again while what it reaches (the database, the object store) is unreachable.

    Retrying the whole task instead would score again, and its chunk, held by this task, would not start.
    """
    deadline, delay = monotonic() + OUTAGE_S, 1.0
    while True:
        try:
            return work()
        except outages as error:
            if monotonic() > deadline:
                raise
            log.warning("%s unreachable, trying again in %.0f s: %s", what, delay, error)
            sleep(delay)
            delay = min(2 * delay, OUTAGE_RETRY_MAX_S)


def _guarded(submission_id: int, run: int, work: Callable[[], str]) -> str:
    """Run `work`; any error but a database or broker outage fails the run (team-safe text), not the task."""
    try:
        return work()
    except INFRASTRUCTURE_ERRORS:
        raise
    except runs.Rejected as rejection:
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
        runs.mark_failed(session, submission_id, run, kind, message, detail)
    log.warning("submission %s run %s failed (%s): %s", submission_id, run, kind, message)
    return "failed"


@app.task(name=SCORE_TASK, bind=True, **RETRY)
def score_submission(self: Task, submission_id: int) -> str:
    """Claim a submission and send its unscored tokens out as chunk tasks (or aggregate, if none is left)."""
    settings = get_settings()
    sessions = _sessions(settings.database_url)
    try:
        with transaction(sessions) as session:
            run = runs.claim_submission(session, submission_id, _worker_name(self))
    except NotFound:
        return f"submission {submission_id}: missing"
    if run is None:
        return f"submission {submission_id}: not active"

    def dispatch() -> str:
        # A run claimed but never planned (this process died in between) is re-planned by the reaper.
        with transaction(sessions) as session:
            plan = runs.plan_run(
                session,
                submission_id,
                run,
                settings.chunk_size,
                engine_provenance(),
                settings.bootstrap_samples,
            )
        if plan.dropped or plan.finished:
            if plan.finished:
                _send_integrity_check(submission_id)
            return "dropped" if plan.dropped else "finished"
        for chunk_id in plan.chunks:  # a chunk recorded but never sent is re-sent by the reaper
            score_chunk.delay(submission_id, run, chunk_id)
        return f"{len(plan.chunks)} chunks"

    return f"submission {submission_id} run {run}: {_guarded(submission_id, run, dispatch)}"


@app.task(name=CHUNK_TASK, bind=True, **RETRY)
def score_chunk(self: Task, submission_id: int, run: int, chunk_id: int) -> str:
    """Score a chunk's tokens under every metric version and seed; aggregate if they were the last."""
    settings = get_settings()
    sessions = _sessions(settings.database_url)
    worker = _worker_name(self)
    with transaction(sessions) as session:
        start = runs.start_chunk(session, chunk_id, run, worker)
    if start.action == runs.StartAction.drop:
        return f"submission {submission_id} run {run}: chunk {chunk_id} dropped"
    if start.action == runs.StartAction.split_up:
        for child in start.children:
            score_chunk.delay(submission_id, run, child)
        return f"submission {submission_id} run {run}: chunk {chunk_id} split into {len(start.children)}"

    def score() -> str:
        with sessions() as session:
            inputs = runs.chunk_inputs(
                session, submission_id, run, start, packs=settings.cache_store is not None
            )
        if inputs is None:
            return "dropped"
        with beating(sessions, chunk_id, worker):
            chunk, scored = _through_outages(lambda: _score(inputs), (StoreUnavailable,), "object store")

        def write() -> str:
            with transaction(sessions) as session:
                return runs.write_chunk(
                    session, chunk, scored, worker, engine_provenance(), settings.bootstrap_samples
                )

        written = _through_outages(write, DATABASE_OUTAGES, "database")
        if written == "scored":  # committed: the split's integrity check may read it
            _send_integrity_check(submission_id)
        return written

    return f"submission {submission_id} run {run}: {_guarded(submission_id, run, score)}"


def _score(inputs: runs.ChunkInputs) -> tuple[runs.ChunkInputs, runs.ScoredChunk]:
    """Score a chunk here, or an isolated one in a process of its own (worker.isolated); return the inputs to
    write it with (a process death on record when that process died) and what was scored."""
    settings = get_settings()

    def score(chunk: runs.ChunkInputs) -> runs.ScoredChunk:
        return runs.score_chunk(chunk, settings.submission_store, settings.cache_dir, settings.cache_store)

    if not inputs.isolated:
        return inputs, score(inputs)
    scored = run_isolated(partial(score, inputs))
    if not isinstance(scored, ProcessDeath):
        return inputs, scored
    log.warning("chunk %s: the process scoring %s alone was %s", inputs.chunk_id, inputs.todo, scored)
    died = replace(inputs, process_death=str(scored))
    return died, score(died)


def _send_integrity_check(submission_id: int, behind_chunks: bool = False) -> None:
    """Ask for the integrity check of a scored entry's split; the run is scored whatever happens to it."""
    try:
        check_integrity.delay(submission_id, behind_chunks)
    except Exception:  # the broker away: the next run's check, or an organiser's, reads this entry too
        log.exception("submission %s: the integrity check after its run could not be sent", submission_id)


@app.task(name=INTEGRITY_TASK, **RETRY)
def check_integrity(submission_id: int, behind_chunks: bool = False) -> str:
    """Check the split of a submission whose run was just scored (server.services.integrity): its flags wait
    for organisers in the admin console; a failed check is recorded there and logged, never failing the run.
    Sent while chunks wait, it goes behind them once (server.runs._after), `behind_chunks` set."""
    settings = get_settings()
    sessions = _sessions(settings.database_url)
    if not behind_chunks:
        with sessions() as session:
            waiting = runs.chunks_waiting(session)
        if waiting:
            _send_integrity_check(submission_id, behind_chunks=True)
            return f"submission {submission_id}: integrity check sent behind the waiting chunks"
    check_id = runs.check_integrity_after_run(sessions, settings, submission_id)
    if check_id is None:
        return f"submission {submission_id}: nothing to check"
    return f"submission {submission_id}: integrity check {check_id}"


def reap_lost_work() -> dict[str, list[int]]:
    """Send again what died or what the broker lost, and fail what cannot finish (server.runs decides)."""
    settings = get_settings()
    sessions = _sessions(settings.database_url)
    now = utc_now()
    with transaction(sessions) as session:
        reaped = runs.reap_dead_chunks(session, now, settings.task_time_limit)
    # A worker may hold what waits in SQL a moment after taking it: only an idle queue proves it lost.
    if not waiting_tasks(settings, declare=True):
        sent_before = now - timedelta(seconds=settings.reaper_interval)
        with transaction(sessions) as session:
            lost = runs.reap_lost_work(session, now, sent_before, settings.max_attempts)
        reaped.chunks += lost.chunks
        reaped.submissions += lost.submissions
        reaped.failed += lost.failed
    for submission_id, chunk_run, chunk_id in reaped.chunks:
        score_chunk.delay(submission_id, chunk_run, chunk_id)
    for submission_id in reaped.submissions:
        score_submission.delay(submission_id)
    if reaped.chunks or reaped.submissions or reaped.failed:
        log.warning(
            "reaper: re-sent chunks %s and submissions %s, failed %s",
            reaped.chunks,
            reaped.submissions,
            reaped.failed,
        )
    # Housekeeping last: the work above (failing a run past the hard limit above all) never waits on it.
    pruned = prune_embedded_broker(settings)
    if pruned:
        log.info("reaper: deleted %d delivered messages from the embedded broker", pruned)
    return {
        "chunks": [chunk_id for _, _, chunk_id in reaped.chunks],
        "submissions": reaped.submissions,
        "failed": reaped.failed,
    }
