"""Liveness written to the database every HEARTBEAT_SECONDS: each worker's, and each running chunk's.

Celery's own ping is a broadcast, which the embedded broker cannot send; the database every worker already
uses can say who runs. A consumer bootstep starts one thread per worker (the main process, not the pool):
it records the worker at start and every HEARTBEAT_SECONDS, keeps going through database outages (a beat
that fails is logged and retried), and removes the worker when it stops. The pool process scoring a chunk
beats for that chunk the same way (`beating`): when the process dies, whatever killed it, the beat stops
and the reaper sends the chunk again (server.runs).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import ClassVar

from celery import bootsteps
from sqlalchemy.orm import Session, sessionmaker

from server.db import make_engine, make_session_factory, transaction
from server.models import utc_now
from server.runs import beat_chunk
from server.services.workers import HEARTBEAT_SECONDS, forget_worker, record_heartbeat
from server.settings import get_settings

log = logging.getLogger(__name__)


def _write_beat(sessions: sessionmaker[Session], write: Callable[[Session], None], what: str) -> None:
    """Write one beat in its own transaction; a failed one (the database is away) is logged, not fatal."""
    try:
        with transaction(sessions) as session:
            write(session)
    except Exception:
        log.warning("%s not written", what, exc_info=True)


def _beat_until(
    stop: threading.Event, sessions: sessionmaker[Session], write: Callable[[Session], None], what: str
) -> None:
    """Write a beat every HEARTBEAT_SECONDS until `stop` is set."""
    while not stop.wait(HEARTBEAT_SECONDS):
        _write_beat(sessions, write, what)


class DatabaseHeartbeat(bootsteps.StartStopStep):
    """Start the heartbeat thread with the consumer; stop it, and forget the worker, on shutdown."""

    requires: ClassVar[set[str]] = {"celery.worker.consumer.connection:Connection"}

    def __init__(self, parent: object, **kwargs: object) -> None:
        super().__init__(parent, **kwargs)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._name = ""

    def start(self, parent: object) -> None:
        if self._thread is not None and self._thread.is_alive():
            return  # the consumer restarts its steps when the broker connection comes back
        self._name = str(parent.hostname)  # type: ignore[attr-defined]
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="database-heartbeat", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        engine = make_engine(get_settings().database_url)
        sessions = make_session_factory(engine)
        started_at = utc_now()

        def record(session: Session) -> None:
            record_heartbeat(session, self._name, started_at)

        what = f"heartbeat of {self._name}"
        try:
            _write_beat(sessions, record, what)
            _beat_until(self._stop, sessions, record, what)
            with transaction(sessions) as session:
                forget_worker(session, self._name)
        except Exception:
            log.warning("heartbeat of %s not removed", self._name, exc_info=True)
        finally:
            engine.dispose()

    def stop(self, parent: object) -> None:
        self._stop.set()

    def shutdown(self, parent: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2 * HEARTBEAT_SECONDS)


@contextmanager
def beating(sessions: sessionmaker[Session], chunk_id: int, worker: str) -> Iterator[None]:
    """Beat for chunk `chunk_id`, held by `worker`, every HEARTBEAT_SECONDS while the block runs."""
    stop = threading.Event()

    def beat(session: Session) -> None:
        beat_chunk(session, chunk_id, worker)

    thread = threading.Thread(
        target=_beat_until,
        args=(stop, sessions, beat, f"beat of chunk {chunk_id}"),
        name=f"chunk-{chunk_id}-beat",
        daemon=True,
    )
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
