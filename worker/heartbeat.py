"""Liveness written to the database every HEARTBEAT_SECONDS: each worker's, and each running chunk's.

Celery's own ping is a broadcast, which the embedded broker cannot send; the database every worker already
uses can say who runs. A consumer bootstep starts one thread per worker (the main process, not the pool):
it records the worker at start and every HEARTBEAT_SECONDS, keeps going through database outages (a beat
that fails is logged and retried), and removes the worker when it stops. The pool process scoring a chunk
beats for that chunk the same way (`beating`): when the process dies, whatever killed it, the beat stops
and the reaper sends the chunk again (server.services.chunks).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import ClassVar

from celery import bootsteps
from sqlalchemy.orm import Session, sessionmaker

from server.db import make_engine, make_session_factory, transaction
from server.models import utc_now
from server.services.chunks import beat_chunk
from server.services.workers import HEARTBEAT_SECONDS, forget_worker, record_heartbeat
from server.settings import get_settings

log = logging.getLogger(__name__)


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
        try:
            while True:
                try:
                    with transaction(sessions) as session:
                        record_heartbeat(session, self._name, started_at)
                except Exception:
                    log.warning("heartbeat of %s not written", self._name, exc_info=True)
                if self._stop.wait(HEARTBEAT_SECONDS):
                    break
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

    def run() -> None:
        while not stop.wait(HEARTBEAT_SECONDS):
            try:
                with transaction(sessions) as session:
                    beat_chunk(session, chunk_id, worker)
            except Exception:
                log.warning("beat of chunk %s not written", chunk_id, exc_info=True)

    thread = threading.Thread(target=run, name=f"chunk-{chunk_id}-beat", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
