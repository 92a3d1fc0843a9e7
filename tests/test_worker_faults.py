"""Faults with real processes: worker processes killed mid-chunk (a consumer, the supervisor), a consumer killed
idle, while it writes, or with the reaper, a consumer wedged while it holds work, a token that kills its worker
every time, a chunk past the hard time limit, a graceful shutdown, a Redis broker flushed and restarted under
load, and chaos: every kind of process killed at random moments, and Redis and PostgreSQL killed and paused.
Each time the submission ends with exactly one result set, equal to the engine's, or fails with the reason
and is refunded; nothing is lost and nothing is scored twice.

The workers run tests/fault_worker.py's app, which injects the faults named in the environment. A test that
stops a server starts its own instance, on its own port and data directory.
"""

from __future__ import annotations

import os
import random
import signal
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager, nullcontext
from datetime import timedelta
from pathlib import Path

import pytest
from own_servers import OwnPostgres, OwnRedis, own_postgres, own_redis, paused
from scratch import scratch_redis_queue
from server_testing import fresh_postgres_database
from sqlalchemy import select
from worker_testing import (
    Service,
    SplitFixture,
    alive,
    assert_scored_once,
    fault_worker_command,
    predictions,
    running_service,
    supervised_processes,
    wait_for,
)

from navsim_lb.processes import child_process
from scorer.versions import LOG_REPLAY_VERSIONS as VERSIONS
from server.db import transaction
from server.main import DATABASE_DOWN
from server.models import ChunkState, FailureKind, ScoringChunk, Status, TokenResultRow, utc_now
from server.runs._score import POISONED_TOKEN
from server.services.workers import LIVE_WITHIN_S

REDIS_URL = os.environ.get("NAVSIM_LB_TEST_REDIS", "redis://127.0.0.1:6379/0")
# The promise: a killed worker costs a submission at most two minutes, with the default settings.
RECOVERY_S = 120.0
OUTAGE_S = 20.0
BACKENDS = ["embedded", pytest.param("postgresql+redis", marks=pytest.mark.services)]
# Each test appends how long its recovery took: docs/reliability.md quotes the last run.
FIGURES = Path(__file__).parent / "artifacts" / "reliability-figures.txt"


def _record(case: str, since: float) -> None:
    FIGURES.parent.mkdir(parents=True, exist_ok=True)
    with FIGURES.open("a") as figures:
        figures.write(f"{case}: {time.monotonic() - since:.1f} s\n")


@contextmanager
def _backend(kind: str) -> Iterator[dict[str, str]]:
    """Yield the settings of the embedded defaults, or of a fresh PostgreSQL database and a Redis queue."""
    if kind == "embedded":
        yield {}
        return
    with (
        fresh_postgres_database() as database_url,
        scratch_redis_queue(REDIS_URL, "navsim-lb-faults") as queue,
    ):
        yield {"DATABASE_URL": database_url, "BROKER_URL": REDIS_URL, "QUEUE_NAME": queue}


def _chunks(service: Service, submission_id: int) -> list[ScoringChunk]:
    with service.factory() as session:
        query = (
            select(ScoringChunk).where(ScoringChunk.submission_id == submission_id).order_by(ScoringChunk.id)
        )
        return list(session.scalars(query).all())


def _running_chunk(service: Service, *submission_ids: int) -> ScoringChunk:
    """Wait until a chunk of one of the submissions is being scored; return it."""
    return wait_for(  # type: ignore[return-value]
        lambda: next(
            (c for s in submission_ids for c in _chunks(service, s) if c.state == ChunkState.running), None
        ),
        f"a chunk of submission {' or '.join(map(str, submission_ids))} to run",
    )


@pytest.mark.parametrize("victim", ["pool process", "main process"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_a_worker_process_killed_mid_chunk_costs_under_two_minutes(
    backend: str, victim: str, tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    faults = {"FAULT_CHUNK_SECONDS": "2", "CHUNK_SIZE": "4"}
    with (
        _backend(backend) as settings,
        running_service(tmp_path, synthetic_split, settings | faults, faults=True) as service,
    ):
        entry = predictions(synthetic_split.directory, seeds=1, noise=0.3, method=f"{victim} killed")
        submission_id = service.upload(entry)
        chunk = _running_chunk(service, submission_id)
        assert chunk.worker is not None
        supervisor: AbstractContextManager[object] = nullcontext()
        killed = time.monotonic()
        if victim == "pool process":
            os.kill(int(chunk.worker.rsplit("/", 1)[1]), signal.SIGKILL)
        else:  # the worker and its beat; its pool processes are orphans
            service.worker.send_signal(signal.SIGKILL)
            service.worker.wait()
            # What a supervisor (systemd, a container's restart policy) does: start the worker again.
            command = fault_worker_command(2, True, "second")
            supervisor = child_process(command, service.env, service.logs / "second-worker.log")
        with supervisor:
            service.final(submission_id, timeout=RECOVERY_S)
        _record(f"{victim} killed ({backend}): kill to scored", killed)
        assert_scored_once(service, synthetic_split, submission_id, entry)
        if victim == "pool process":
            assert {c.deaths for c in _chunks(service, submission_id) if c.id == chunk.id} == {1}
            assert service.worker.poll() is None  # the worker replaced its pool process and went on
            # billiard's own report of the death is a log line like any other, with the run's fields
            assert "Logging error" not in service.worker_log()


def _kill(*pids: int) -> None:
    for pid in pids:
        os.kill(pid, signal.SIGKILL)


@pytest.mark.parametrize("moment", ["consumers idle", "consumer writing", "reaper and consumer scoring"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_a_kill_at_any_moment_is_recovered_within_a_minute(
    backend: str, moment: str, tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    """No kill wedges a worker: consumers killed while they wait for work (all of them), while one writes its
    rows (inside the transaction), or the reaper with the consumer scoring a chunk, whose re-send then waits
    for the reaper started again. The supervisor starts each again; every row is written exactly once."""
    marker = tmp_path / "writing"
    faults = {"FAULT_CHUNK_SECONDS": "1", "CHUNK_SIZE": "4", "REAPER_INTERVAL": "5"}
    if moment == "consumer writing":
        faults |= {"FAULT_WRITE_MARKER": str(marker), "FAULT_WRITE_SECONDS": "3"}
    with (
        _backend(backend) as settings,
        running_service(tmp_path, synthetic_split, settings | faults, faults=True) as service,
    ):
        entry = predictions(synthetic_split.directory, seeds=1, noise=0.3, method=moment)
        consumers, reapers = supervised_processes(service.worker.pid)
        if moment == "consumers idle":
            before = predictions(synthetic_split.directory, seeds=1, noise=0.2, method="before the kill")
            before_id = service.upload(before)
            service.final(before_id)
            killed = time.monotonic()
            _kill(*consumers)
            submission_id = service.upload(entry)
        elif moment == "consumer writing":
            submission_id = service.upload(entry)
            victim = int(wait_for(lambda: marker.exists() and marker.read_text(), "a chunk to write"))  # type: ignore[arg-type]
            killed = time.monotonic()
            _kill(victim)
        else:
            submission_id = service.upload(entry)
            chunk = _running_chunk(service, submission_id)
            assert chunk.worker is not None
            killed = time.monotonic()
            _kill(int(chunk.worker.rsplit("/", 1)[1]), *reapers)
        service.final(submission_id, timeout=RECOVERY_S)
        _record(f"{moment} killed ({backend}): kill to scored", killed)
        assert_scored_once(service, synthetic_split, submission_id, entry)
        if moment == "consumers idle":
            assert_scored_once(service, synthetic_split, before_id, before)
        else:  # the killed chunk was handed on once: split, its tokens inheriting its one death
            chunks = _chunks(service, submission_id)
            assert [c.deaths for c in chunks if c.state == ChunkState.split_up] == [1]
            assert max(c.deaths for c in chunks) == 1
        assert service.worker.poll() is None
        now_consumers, now_reapers = supervised_processes(service.worker.pid)
        assert len(now_consumers) == len(consumers) and len(now_reapers) == 1
        if moment != "consumer writing":  # which consumer wrote is not known beforehand
            assert not set(now_consumers + now_reapers) & set(
                consumers if moment == "consumers idle" else reapers
            )


def test_a_consumer_wedged_on_its_work_starves_nothing_and_is_replaced(
    tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    """The only consumer hangs in a chunk where no soft limit reaches it: the reaper, a process of its own, still
    hands on a chunk whose process died meanwhile; the supervisor kills the wedged consumer at the hard limit and
    starts another, which scores the next submission."""
    wedged = predictions(synthetic_split.directory, seeds=1, noise=0.3, method="wedged")
    after = predictions(synthetic_split.directory, seeds=1, noise=0.4, method="after the wedge")
    faults = {
        "FAULT_HANG_TOKEN": min(wedged.seeds[0]),
        "FAULT_HANG_MARKER": str(tmp_path / "hanging"),  # the next submission's chunk does not hang
        "CHUNK_SIZE": "4",
        "TASK_TIME_LIMIT": "35",
        "REAPER_INTERVAL": "2",
    }
    with running_service(tmp_path, synthetic_split, faults, concurrency=1, faults=True) as service:
        wedged_id = service.upload(wedged)
        hung: ScoringChunk = wait_for(  # type: ignore[assignment]
            lambda: next(
                (
                    c
                    for c in _chunks(service, wedged_id)
                    if c.state == ChunkState.running and faults["FAULT_HANG_TOKEN"] in c.tokens
                ),
                None,
            ),
            "the chunk that hangs to run",
        )
        assert hung.worker is not None
        consumer = int(hung.worker.rsplit("/", 1)[1])
        after_id = service.upload(after)  # waits in the queue behind the wedged consumer
        with transaction(service.factory) as session:  # another chunk, as if its process died a while ago
            lost = session.scalar(
                select(ScoringChunk)
                .where(ScoringChunk.submission_id == wedged_id, ScoringChunk.id != hung.id)
                .order_by(ScoringChunk.id)
                .limit(1)
            )
            assert lost is not None
            long_ago = utc_now() - timedelta(seconds=LIVE_WITHIN_S + 5)
            lost.state, lost.worker, lost.started_at, lost.beat_at = (
                ChunkState.running,
                "gone/1",
                long_ago,
                long_ago,
            )
            lost_id = lost.id
        forged = time.monotonic()
        wait_for(
            lambda: any(c.id == lost_id and c.deaths == 1 for c in _chunks(service, wedged_id)),
            "the reaper to hand on the dead chunk",
        )
        _record("reaper while the only consumer is wedged: dead chunk to re-sent", forged)
        assert alive(consumer)  # the reaper did not wait for it
        assert {c.state for c in _chunks(service, wedged_id) if c.id == hung.id} == {ChunkState.running}
        wait_for(lambda: not alive(consumer), "the supervisor to kill the wedged consumer")
        replaced = time.monotonic()
        failed = service.final(wedged_id, timeout=RECOVERY_S)
        assert (failed.status, failed.charged) == (Status.failed, False)
        assert "hard time limit of 35 s" in (failed.error or "")
        service.final(after_id, timeout=RECOVERY_S)
        _record("wedged consumer killed at the hard limit: kill to the next submission scored", replaced)
        assert_scored_once(service, synthetic_split, after_id, after)
        assert service.worker.poll() is None


CHAOS_SUBMISSIONS = 3
CHAOS_KILLS = 6
CHAOS_GAP_S = (1.0, 5.0)
CHAOS_PROCESSES = ["consumer", "consumer", "reaper", "supervisor"]
# On PostgreSQL + Redis, each server is also killed once and paused once, at random moments among the kills.
CHAOS_SERVER_FAULTS = ["redis killed", "redis paused", "postgresql killed", "postgresql paused"]
CHAOS_OUTAGE_S = (1.0, 5.0)  # how long a killed server stays down, a paused one paused

OwnServers = tuple[OwnPostgres, OwnRedis]


@contextmanager
def _chaos_backend(kind: str, tmp_path: Path) -> Iterator[tuple[dict[str, str], OwnServers | None]]:
    """Yield the settings of the embedded defaults, or of a PostgreSQL and a Redis of the test's own (which it
    kills and pauses), with those servers."""
    if kind == "embedded":
        yield {}, None
        return
    with own_postgres() as database, own_redis(tmp_path / "redis") as broker:
        yield {"DATABASE_URL": database.url, "BROKER_URL": broker.url}, (database, broker)


def _server_fault(fault: str, servers: OwnServers, outage_s: float) -> None:
    """Kill a server and start it again after `outage_s` (Redis comes back empty: it keeps nothing), or pause
    it for that long."""
    database, broker = servers
    server: OwnPostgres | OwnRedis = database if fault.startswith("postgresql") else broker
    if fault.endswith("paused"):
        with paused(server.pids()):
            time.sleep(outage_s)
        return
    server.kill()
    time.sleep(outage_s)
    server.start()


@pytest.mark.parametrize("backend", BACKENDS)
def test_chaos_random_kills_while_several_submissions_are_scored(
    backend: str, tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    """Consumers, the reaper and the supervisor itself SIGKILLed at random moments while three submissions are
    scored (a killed supervisor is started again, as its own supervisor would), and on PostgreSQL + Redis
    each server killed and paused: at the end each submission is scored once, every row exactly once, no
    chunk left running. CHAOS_SEED replays a run; a failure names its seed."""
    seed = int(os.environ.get("CHAOS_SEED", str(random.SystemRandom().randrange(2**32))))
    rng = random.Random(seed)
    replay = f"replay with CHAOS_SEED={seed}"
    print(replay)  # pytest shows it beside any failure
    faults = {"FAULT_CHUNK_SECONDS": "1.5", "CHUNK_SIZE": "4", "REAPER_INTERVAL": "3"}
    entries = [
        predictions(synthetic_split.directory, seeds=2, noise=0.2 + 0.1 * index, method=f"chaos {index}")
        for index in range(CHAOS_SUBMISSIONS)
    ]
    with (
        _chaos_backend(backend, tmp_path) as (settings, servers),
        running_service(tmp_path, synthetic_split, settings | faults, faults=True) as service,
        ExitStack() as restarted,
    ):
        victims = [rng.choice(CHAOS_PROCESSES) for _ in range(CHAOS_KILLS)]
        victims += CHAOS_SERVER_FAULTS if servers is not None else []
        rng.shuffle(victims)
        supervisor = service.worker
        ids = [service.upload(entry) for entry in entries]
        for index, victim in enumerate(victims):
            time.sleep(rng.uniform(*CHAOS_GAP_S))
            consumers, reapers = supervised_processes(supervisor.pid)
            if victim in CHAOS_SERVER_FAULTS:
                assert servers is not None
                _server_fault(victim, servers, rng.uniform(*CHAOS_OUTAGE_S))
            elif victim == "supervisor":
                supervisor.kill()
                supervisor.wait()
                command = fault_worker_command(2, True, f"chaos{index}")
                log = service.logs / f"chaos-worker-{index}.log"
                supervisor = restarted.enter_context(child_process(command, service.env, log))
            else:
                candidates = consumers if victim == "consumer" else reapers
                if candidates:  # none while the supervisor starts them again
                    os.kill(rng.choice(candidates), signal.SIGKILL)
        last_fault = time.monotonic()
        for submission_id in ids:
            try:
                service.final(submission_id, timeout=RECOVERY_S)
            except pytest.fail.Exception as error:
                raise AssertionError(f"{replay}: submission {submission_id}: {error}") from error
        _record(f"chaos ({backend}, {', '.join(victims)}): last fault to all scored", last_fault)
        for submission_id, entry in zip(ids, entries, strict=True):
            try:
                assert_scored_once(service, synthetic_split, submission_id, entry)
            except AssertionError as error:
                raise AssertionError(f"{replay}: submission {submission_id}: {error}") from error
        running = [c.id for i in ids for c in _chunks(service, i) if c.state == ChunkState.running]
        assert running == [], replay


# On PostgreSQL + Redis, where Celery also hands the killed chunk back at once: a duplicate that must drop.
@pytest.mark.parametrize("backend", [BACKENDS[1]])
def test_a_token_that_kills_its_worker_every_time_fails_alone(
    backend: str, tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    entry = predictions(synthetic_split.directory, seeds=2, noise=0.3, method="poisoned")
    poison = sorted(entry.seeds[0])[5]
    faults = {"FAULT_POISON_TOKEN": poison, "CHUNK_SIZE": "8", "REAPER_INTERVAL": "2"}
    with (
        _backend(backend) as settings,
        running_service(tmp_path, synthetic_split, settings | faults, faults=True) as service,
    ):
        uploaded = time.monotonic()
        submission_id = service.upload(entry)
        submission = service.final(submission_id, timeout=RECOVERY_S)
        _record(f"poisoned token ({backend}): upload to scored", uploaded)
        assert submission.status == Status.scored, (submission.error, submission.error_detail)
        with service.factory() as session:
            rows = session.scalars(
                select(TokenResultRow).where(TokenResultRow.submission_id == submission_id)
            ).all()
        assert len(rows) == len(entry.seeds[0]) * 2 * len(VERSIONS)
        failed = {(row.token, row.error) for row in rows if not row.valid}
        assert failed == {(poison, POISONED_TOKEN)}
        # named for the admins, with what its isolated process died of
        assert f"token {poison}: written as failed, its process killed by SIGKILL" in (
            submission.error_detail or ""
        )
        with service.client() as client:  # the team sees the token failed, and why
            seen = client.get(
                f"/api/v1/submissions/{submission_id}/tokens", params={"version": "v1.1"}
            ).json()
        assert [row["error"] for row in seen if not row["valid"]] == [POISONED_TOKEN] * 2
        assert service.result(submission_id, "v1.1")["failed_tokens"] == 1
        deaths = sorted(
            (len(c.tokens), c.deaths, c.state) for c in _chunks(service, submission_id) if c.deaths
        )
        assert deaths[-1] == (4, 1, ChunkState.split_up) and (1, 2, ChunkState.failed) in deaths


def _holder(chunk: ScoringChunk) -> int:
    """Return the pid of the consumer holding a running chunk."""
    assert chunk.worker is not None
    return int(chunk.worker.rsplit("/", 1)[1])


def test_kills_from_outside_never_fail_a_token_however_often_they_land_on_it(
    tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    """The consumer holding a chunk killed, then twice the consumer holding one of its tokens, scored again
    alone: the token is scored as any other. Only a process that dies of the token, seen dying by the consumer
    that forked it for the token, fails it."""
    faults = {"FAULT_CHUNK_SECONDS": "2", "CHUNK_SIZE": "4", "REAPER_INTERVAL": "2"}
    with running_service(tmp_path, synthetic_split, faults, faults=True) as service:
        entry = predictions(synthetic_split.directory, seeds=1, noise=0.3, method="killed from outside")
        uploaded = time.monotonic()
        submission_id = service.upload(entry)
        chunk = _running_chunk(service, submission_id)
        killed = {_holder(chunk)}
        _kill(*killed)
        token = chunk.tokens[0]

        def alone() -> ScoringChunk | None:  # the token's own chunk, taken by a consumer not yet killed
            return next(
                (
                    c
                    for c in _chunks(service, submission_id)
                    if c.tokens == [token] and c.state == ChunkState.running and _holder(c) not in killed
                ),
                None,
            )

        for _ in range(2):
            holder = _holder(wait_for(alone, f"{token} to be scored alone"))  # type: ignore[arg-type]
            killed.add(holder)
            _kill(holder)
        service.final(submission_id, timeout=RECOVERY_S)
        _record("a token's consumer killed three times from outside: upload to scored", uploaded)
        assert_scored_once(service, synthetic_split, submission_id, entry)
        with service.factory() as session:
            failed = session.scalars(
                select(TokenResultRow.token).where(
                    TokenResultRow.submission_id == submission_id, ~TokenResultRow.valid
                )
            ).all()
        assert failed == []
        [scored_alone] = [c for c in _chunks(service, submission_id) if c.tokens == [token]]
        assert (scored_alone.state, scored_alone.deaths, scored_alone.starts) == (ChunkState.done, 3, 3)


def test_a_chunk_past_the_hard_time_limit_fails_the_run_refunded(
    tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    entry = predictions(synthetic_split.directory, seeds=1, noise=0.3, method="hangs")
    # A 31 s limit leaves chunks a 1 s soft limit; planning and the reaper outlast it, and must not be cut by
    # it (an exception raised inside a broker write can leave the embedded broker's file locked).
    faults = {
        "FAULT_HANG_TOKEN": min(entry.seeds[0]),
        "TASK_TIME_LIMIT": "31",
        "REAPER_INTERVAL": "2",
        "FAULT_PLAN_SECONDS": "1.5",
        "FAULT_REAP_SECONDS": "1.5",
    }
    with running_service(tmp_path, synthetic_split, faults, faults=True) as service:
        uploaded = time.monotonic()
        submission_id = service.upload(entry)
        submission = service.final(submission_id, timeout=RECOVERY_S)
        _record("hard time limit of 31 s: upload to failed", uploaded)
    assert (submission.status, submission.failure_kind, submission.charged) == (
        Status.failed,
        FailureKind.infrastructure,
        False,
    )
    assert "hard time limit of 31 s" in (submission.error or "") and "refunded" in (submission.error or "")


def test_a_worker_stopped_with_sigterm_finishes_its_chunk_and_loses_nothing(
    tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    faults = {"FAULT_CHUNK_SECONDS": "2", "CHUNK_SIZE": "4"}
    with running_service(tmp_path, synthetic_split, faults, faults=True) as service:
        entry = predictions(synthetic_split.directory, seeds=1, noise=0.3, method="sigterm")
        submission_id = service.upload(entry)
        chunk = _running_chunk(service, submission_id)
        stopped = time.monotonic()
        service.worker.send_signal(signal.SIGTERM)
        service.worker.wait(timeout=60)
        _record("SIGTERM: signal to worker exit", stopped)
        assert {c.state for c in _chunks(service, submission_id) if c.id == chunk.id} == {ChunkState.done}
        command = fault_worker_command(2, True, "second")
        with child_process(command, service.env, service.logs / "second-worker.log"):
            service.final(submission_id)
        assert_scored_once(service, synthetic_split, submission_id, entry)
        assert all(c.deaths == 0 for c in _chunks(service, submission_id))


@pytest.mark.services
def test_a_redis_broker_flushed_then_restarted_under_load_loses_nothing(
    tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    faults = {"FAULT_CHUNK_SECONDS": "1", "CHUNK_SIZE": "4", "REAPER_INTERVAL": "5"}
    entries = [
        predictions(synthetic_split.directory, seeds=1, noise=0.2 + 0.1 * index, method=f"broker {index}")
        for index in range(3)
    ]
    with fresh_postgres_database() as database_url, own_redis(tmp_path / "redis") as broker:
        settings = {"DATABASE_URL": database_url, "BROKER_URL": broker.url}
        with running_service(tmp_path, synthetic_split, settings | faults, faults=True) as service:
            ids = [service.upload(entry) for entry in entries]
            _running_chunk(service, ids[0])
            broker.client().flushall()  # a broker that lost its queue: the others wait in SQL only
            # Work goes on from SQL. The workers may have planned and scored the others before the first one's
            # chunk ran (their chunks then all done before the flush): a chunk of theirs running or done shows it.
            wait_for(
                lambda: any(
                    c.state in (ChunkState.running, ChunkState.done)
                    for s in ids[1:]
                    for c in _chunks(service, s)
                ),
                f"a chunk of submission {ids[1]} or {ids[2]} to run or be done",
            )
            restarted = time.monotonic()
            broker.restart()
            for submission_id in ids:
                service.final(submission_id, timeout=RECOVERY_S)
            _record("redis flushed, then restarted: restart to all three scored", restarted)
            for submission_id, entry in zip(ids, entries, strict=True):
                assert_scored_once(service, synthetic_split, submission_id, entry)


@pytest.mark.services
def test_a_database_down_for_twenty_seconds_is_a_503_and_everything_recovers(
    tmp_path: Path, synthetic_split: SplitFixture
) -> None:
    faults = {"FAULT_CHUNK_SECONDS": "2", "CHUNK_SIZE": "4", "REAPER_INTERVAL": "5"}
    entry = predictions(synthetic_split.directory, seeds=1, noise=0.3, method="database outage")
    with own_postgres() as database, scratch_redis_queue(REDIS_URL, "navsim-lb-faults") as queue:
        settings = {"DATABASE_URL": database.url, "BROKER_URL": REDIS_URL, "QUEUE_NAME": queue}
        with running_service(tmp_path, synthetic_split, settings | faults, faults=True) as service:
            submission_id = service.upload(entry)
            _running_chunk(service, submission_id)
            database.stop()
            stopped = time.monotonic()
            with service.client() as client:
                while time.monotonic() - stopped < OUTAGE_S:
                    board = client.get("/api/v1/leaderboard", params={"phase": "test"})
                    assert board.status_code == 503, board.text
                    assert board.json() == {"detail": DATABASE_DOWN} and board.headers["Retry-After"]
                    upload = client.post("/api/v1/submissions", files={"file": ("late.json", b"{}")})
                    assert upload.status_code == 503, upload.text
                    page = client.get("/")
                    assert page.status_code == 503 and "not answering" in page.text
                    time.sleep(1)
            database.start()
            started = time.monotonic()
            service.final(submission_id, timeout=RECOVERY_S)
            _record("postgresql down 20 s: restart to scored", started)
            assert_scored_once(service, synthetic_split, submission_id, entry)
            after = predictions(synthetic_split.directory, seeds=1, noise=0.4, method="after the outage")
            after_id = service.upload(after)
            service.final(after_id)
            assert_scored_once(service, synthetic_split, after_id, after)
            assert service.worker.poll() is None  # no restart was needed
