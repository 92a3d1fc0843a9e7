"""Worker heartbeats in the database: recent ones count as live workers, old ones age out, a stop forgets."""

from __future__ import annotations

from datetime import timedelta

from server_testing import World

from server.db import transaction
from server.models import utc_now
from server.services.workers import LIVE_WITHIN_S, forget_worker, record_heartbeat, workers_from_heartbeats


def test_recent_heartbeats_are_live_workers_and_old_ones_age_out(world: World) -> None:
    now = utc_now()
    with transaction(world.factory) as session:
        record_heartbeat(session, "celery@a", now - timedelta(minutes=5), now - timedelta(seconds=1))
        record_heartbeat(
            session, "celery@killed", now - timedelta(minutes=5), now - timedelta(seconds=LIVE_WITHIN_S + 1)
        )
    with world.session() as session:
        live = workers_from_heartbeats(session, now)
    assert (live["ok"], live["count"], live["names"]) == (True, 1, ["celery@a"])
    with transaction(world.factory) as session:
        record_heartbeat(
            session, "celery@a", now - timedelta(minutes=5), now
        )  # the same worker again: one row
        forget_worker(session, "celery@killed")
    with world.session() as session:
        assert workers_from_heartbeats(session, now)["names"] == ["celery@a"]
        forget_worker(session, "celery@a")
        session.commit()
        gone = workers_from_heartbeats(session, now)
    assert (gone["ok"], gone["count"]) == (False, 0) and "(none)" in gone["detail"]
