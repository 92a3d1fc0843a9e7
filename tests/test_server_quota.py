"""Quotas, duplicates and idempotency of the create path (service level), including two uploads racing for
the last slot on SQLite and on PostgreSQL."""

from __future__ import annotations

import threading
from datetime import timedelta
from pathlib import Path

import pytest
from server_testing import World, add_phase, add_team, factory_for, phase_row, team_row, upload_of
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from server.db import transaction
from server.migrate import upgrade
from server.models import FailureKind, Submission, utc_now
from server.object_store import LocalStore, ObjectStore
from server.runs import cancel, claim_submission, mark_failed
from server.services.errors import Conflict, Forbidden, QuotaExceeded
from server.services.quota import next_utc_midnight, quota_usage
from server.services.submissions import create_submission
from server.services.teams import set_team_quota


def _submit(
    world: World, payload: bytes, phase: str = "test", key: str | None = None, now=None
) -> tuple[int, bool]:
    with transaction(world.factory) as session:
        submission, replayed = create_submission(
            session,
            team_row(session, world.team_id),
            phase_row(session, phase),
            upload_of(payload),
            world.settings.submission_store,
            key,
            now,
        )
        return submission.id, replayed


def _count(world: World) -> int:
    with world.session() as session:
        return session.scalar(select(func.count()).select_from(Submission)) or 0


def test_per_day_quota_resets_at_utc_midnight(world: World) -> None:
    add_phase(world.factory, "daily", per_day=2)
    now = utc_now()
    _submit(world, b"1", "daily", now=now)
    _submit(world, b"2", "daily", now=now)
    with pytest.raises(QuotaExceeded) as caught:
        _submit(world, b"3", "daily", now=now)
    assert (caught.value.quota, caught.value.limit, caught.value.used) == ("per_day", 2, 2)
    assert caught.value.resets_at == next_utc_midnight(now)
    assert "per UTC day" in caught.value.message and "resets at" in caught.value.message
    assert _count(world) == 2
    _submit(world, b"3", "daily", now=next_utc_midnight(now) + timedelta(seconds=1))
    assert _count(world) == 3


def test_total_quota_and_team_override(world: World) -> None:
    add_phase(world.factory, "short", total=1)
    _submit(world, b"1", "short")
    with pytest.raises(QuotaExceeded) as caught:
        _submit(world, b"2", "short")
    assert caught.value.quota == "total" and caught.value.resets_at is None
    with transaction(world.factory) as session:
        set_team_quota(session, world.team_id, phase_row(session, "short"), None, 2, None)
    _submit(world, b"2", "short")
    with pytest.raises(QuotaExceeded):
        _submit(world, b"3", "short")


def test_in_flight_quota_frees_when_a_run_ends(world: World) -> None:
    add_phase(world.factory, "busy", in_flight=1)
    first, _ = _submit(world, b"1", "busy")
    with pytest.raises(QuotaExceeded) as caught:
        _submit(world, b"2", "busy")
    assert caught.value.quota == "in_flight"
    with transaction(world.factory) as session:
        run = claim_submission(session, first, "w1")
        assert run == 1
        mark_failed(session, first, run, FailureKind.submission, "poses diverge")
    _submit(world, b"2", "busy")


def test_infrastructure_failures_and_cancellations_are_refunded(world: World) -> None:
    add_phase(world.factory, "two", total=2)
    infra, _ = _submit(world, b"1", "two")
    user, _ = _submit(world, b"2", "two")
    with transaction(world.factory) as session:
        mark_failed(session, infra, 1, FailureKind.infrastructure, "worker lost", detail="OOM on host-3")
        mark_failed(session, user, 1, FailureKind.submission, "every token failed")
    cancelled, _ = _submit(world, b"3", "two")
    with transaction(world.factory) as session:
        cancel(session, session.get(Submission, cancelled))
        usage = {u.name: u.used for u in quota_usage(session, world.team_id, phase_row(session, "two"))}
        refunded = session.get(Submission, infra)
        assert refunded is not None and not refunded.charged and "refunded" in (refunded.error or "")
        assert "OOM" not in (refunded.error or "") and refunded.error_detail == "OOM on host-3"
    assert usage["total"] == 1  # only the submission-caused failure counts
    _submit(world, b"4", "two")
    with pytest.raises(QuotaExceeded):
        _submit(world, b"5", "two")


def test_same_file_is_not_scored_twice_unless_its_run_failed(world: World) -> None:
    first, _ = _submit(world, b"same")
    with pytest.raises(Conflict) as caught:
        _submit(world, b"same")
    assert caught.value.extra["submission_id"] == first
    with transaction(world.factory) as session:
        mark_failed(session, first, 1, FailureKind.infrastructure, "broker lost")
    again, _ = _submit(world, b"same")
    assert again != first
    other_team, _ = add_team(world.factory, "beta")
    with transaction(world.factory) as session:
        create_submission(
            session,
            team_row(session, other_team),
            phase_row(session, "test"),
            upload_of(b"same"),
            world.settings.submission_store,
        )


def test_idempotency_key_replays_without_using_quota(world: World) -> None:
    add_phase(world.factory, "one", total=1)
    first, replayed = _submit(world, b"1", "one", key="k-1")
    assert not replayed
    again, replayed = _submit(world, b"1", "one", key="k-1")
    assert (again, replayed) == (first, True)
    with pytest.raises(Conflict, match="Idempotency-Key"):
        _submit(world, b"2", "one", key="k-1")
    assert _count(world) == 1


def test_closed_phase_refuses(world: World) -> None:
    add_phase(
        world.factory, "over", opens_at=utc_now() - timedelta(days=3), closes_at=utc_now() - timedelta(days=1)
    )
    with pytest.raises(Forbidden, match="not open"):
        _submit(world, b"1", "over")
    assert _count(world) == 0


def _race_for_last_slot(
    factory: sessionmaker[Session], storage: ObjectStore, team_id: int, racers: int
) -> list[object]:
    """Start `racers` uploads at once in separate sessions; return each one's submission id or exception."""
    barrier = threading.Barrier(racers)
    outcomes: list[object] = [None] * racers

    def race(index: int) -> None:
        barrier.wait()
        try:
            with transaction(factory) as session:
                submission, _ = create_submission(
                    session,
                    team_row(session, team_id),
                    phase_row(session, "race"),
                    upload_of(f"racer {index}".encode()),
                    storage,
                )
                outcomes[index] = submission.id
        except Exception as error:  # noqa: BLE001 - collected and checked by the test
            outcomes[index] = error

    threads = [threading.Thread(target=race, args=(i,)) for i in range(racers)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return outcomes


def _check_race(factory: sessionmaker[Session], storage: ObjectStore, team_id: int) -> None:
    with transaction(factory) as session:
        create_submission(
            session, team_row(session, team_id), phase_row(session, "race"), upload_of(b"first"), storage
        )
    outcomes = _race_for_last_slot(factory, storage, team_id, racers=2)
    winners = [o for o in outcomes if isinstance(o, int)]
    losers = [o for o in outcomes if isinstance(o, QuotaExceeded)]
    assert len(winners) == 1 and len(losers) == 1, outcomes
    with factory() as session:
        count = session.scalar(select(func.count()).where(Submission.team_id == team_id)) or 0
    assert count == 2


def test_two_uploads_race_for_the_last_slot_on_sqlite(world: World) -> None:
    add_phase(world.factory, "race", total=2)
    _check_race(world.factory, world.settings.submission_store, world.team_id)


@pytest.mark.services
def test_two_uploads_race_for_the_last_slot_on_postgresql(postgres_url: str, tmp_path: Path) -> None:
    upgrade(postgres_url)
    factory = factory_for(postgres_url)
    team_id, _ = add_team(factory, "alpha")
    add_phase(factory, "race", total=2)
    for _ in range(5):  # several rounds: each must have exactly one winner
        _check_race(factory, LocalStore(tmp_path), team_id)
        with transaction(factory) as session:
            session.query(Submission).delete()
    factory.kw["bind"].dispose()
