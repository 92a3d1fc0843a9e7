"""Worker heartbeats in the database: written by each worker, read by health and the admin console.

Celery's ping needs a broadcast the embedded broker (kombu's SQL transport) cannot send, so every worker
also records itself here every HEARTBEAT_SECONDS; a worker seen within LIVE_WITHIN_S is alive.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from server.models import WorkerHeartbeat, utc_now

HEARTBEAT_SECONDS = 5.0
LIVE_WITHIN_S = 4 * HEARTBEAT_SECONDS  # a missed beat or two is not death


def record_heartbeat(session: Session, name: str, started_at: datetime, now: datetime | None = None) -> None:
    """Record that worker `name` (started at `started_at`) is alive now."""
    session.merge(WorkerHeartbeat(name=name, started_at=started_at, seen_at=now or utc_now()))


def forget_worker(session: Session, name: str) -> None:
    """Remove a worker that stops (a killed one simply ages out)."""
    session.execute(delete(WorkerHeartbeat).where(WorkerHeartbeat.name == name))


def workers_from_heartbeats(session: Session, now: datetime | None = None) -> dict[str, Any]:
    """Return the workers seen recently, shaped as the health check's `workers` entry."""
    since = (now or utc_now()) - timedelta(seconds=LIVE_WITHIN_S)
    names = sorted(
        session.scalars(select(WorkerHeartbeat.name).where(WorkerHeartbeat.seen_at >= since)).all()
    )
    return {
        "ok": bool(names),
        "count": len(names),
        "names": names,
        "detail": f"the broker cannot broadcast a ping: workers that wrote a heartbeat in the last "
        f"{LIVE_WITHIN_S:.0f} s" + ("" if names else " (none)"),
    }
