"""The service's health as `/health` reports it: the database (and its schema revision), the broker, the workers."""

from __future__ import annotations

from typing import Any

from sqlalchemy import Engine, text
from sqlalchemy.orm import Session

from server.migrate import current_revision
from server.services.workers import workers_from_heartbeats


def health_report(
    session: Session, engine: Engine, broker: dict[str, Any], workers: dict[str, Any]
) -> dict[str, Any]:
    """Return the health body from the database's answer, the broker's status and the workers' ping.

    A broker that cannot broadcast a ping (`workers["ok"]` None) leaves the answer to the workers' heartbeats.
    """
    try:
        session.execute(text("SELECT 1"))
        database = {"ok": True, "revision": current_revision(engine), "detail": ""}
    except Exception as error:  # noqa: BLE001 - health reports, it does not fail
        database = {"ok": False, "revision": None, "detail": f"{type(error).__name__}: {error}"}
    if workers["ok"] is None and database["ok"]:
        workers = workers_from_heartbeats(session)
    healthy = database["ok"] and broker["ok"] and workers["ok"] is not False
    return {
        "status": "ok" if healthy else "degraded",
        "database": database,
        "broker": broker,
        "workers": workers,
    }
