"""The one door from the API to the workers: send a submission's scoring task by name (the worker owns the task)."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from celery import Celery

from server.settings import Settings, get_settings

SCORE_TASK = "worker.tasks.score_submission"


@lru_cache(maxsize=4)
def celery_client(broker_url: str) -> Celery:
    """Return a Celery app used only to send tasks to `broker_url`."""
    return Celery("navsim-lb-api", broker=broker_url)


def enqueue_submission(submission_id: int, settings: Settings | None = None) -> None:
    """Ask a worker to score the current run of a submission."""
    settings = settings or get_settings()
    celery_client(settings.broker_url).send_task(SCORE_TASK, args=[submission_id])


def broker_status(settings: Settings) -> dict[str, Any]:
    """Return whether the broker accepts a connection, with the error when it does not."""
    try:
        with celery_client(settings.broker_url).connection_for_write() as connection:
            connection.ensure_connection(max_retries=1, timeout=2)
    except Exception as error:  # noqa: BLE001 - any failure means "broker down", reported as text
        return {"ok": False, "detail": f"{type(error).__name__}: {error}"}
    return {"ok": True, "detail": ""}


def live_workers(settings: Settings) -> dict[str, Any]:
    """Return the workers answering a ping; `ok` is None when the transport cannot broadcast (embedded broker)."""
    app = celery_client(settings.broker_url)
    try:
        with app.connection_for_read() as connection:
            can_broadcast = "fanout" in connection.transport.implements.exchange_type
            if not can_broadcast:
                return {
                    "ok": None,
                    "count": None,
                    "names": [],
                    "detail": "the broker cannot broadcast a ping",
                }
            replies = app.control.ping(timeout=1.0, connection=connection) or []
    except Exception as error:  # noqa: BLE001 - reported as text, health must answer
        return {
            "ok": False,
            "count": 0,
            "names": [],
            "detail": f"cannot ping workers: {type(error).__name__}: {error}",
        }
    names = sorted(name for reply in replies for name in reply)
    return {
        "ok": bool(names),
        "count": len(names),
        "names": names,
        "detail": "" if names else "no worker answered",
    }
