"""Fixtures and helpers of the server tests: a migrated temporary SQLite database per test, an app whose
queue records what it was asked to score, and short-hands to create splits, phases, teams and tokens
through the services."""

from __future__ import annotations

import hashlib
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from scratch import scratch_postgres_database
from sqlalchemy import create_engine
from sqlalchemy.orm import Session, sessionmaker

from scorer.versions import ALL_RESULT_COLUMNS, LOG_REPLAY_VERSIONS
from server.db import make_engine, make_session_factory, transaction
from server.main import create_app
from server.migrate import upgrade
from server.models import Approval, Phase, Scope, Split, SplitSubset, Submission, Team, utc_now
from server.services.splits import create_phase
from server.services.teams import create_team
from server.services.tokens import create_token
from server.services.validation import ValidUpload
from server.settings import Settings

REFERENCE_DIR = Path(__file__).parent / "fixtures" / "reference"
REFERENCE_SUBMISSIONS = REFERENCE_DIR / "submissions"
POSTGRES_URL = os.environ.get("NAVSIM_LB_TEST_POSTGRES", "postgresql+psycopg://postgres@127.0.0.1:5432/test")


def reference_tokens() -> list[str]:
    """Return the tokens of the reference split, sorted."""
    return sorted(path.name.split(".")[0] for path in (REFERENCE_DIR / "scenes").iterdir())


def split_row(session: Session, name: str = "reference", public_tokens: list[str] | None = None) -> Split:
    """Add the reference scenes as a split row (registration itself is tested with the engine)."""
    tokens = reference_tokens()
    split = Split(name=name, directory=str(REFERENCE_DIR), content_hash="0" * 64, token_count=len(tokens))
    if public_tokens is not None:
        split.subsets = [
            SplitSubset(name="public", tokens=[t for t in tokens if t in public_tokens]),
            SplitSubset(name="private", tokens=[t for t in tokens if t not in public_tokens]),
        ]
    session.add(split)
    session.flush()
    return split


def upload_of(payload: bytes, seeds: int = 1, method: str = "m") -> ValidUpload:
    """Return an accepted upload of `payload` (distinct payloads give distinct sha256)."""
    return ValidUpload(
        data=payload,
        filename="sub.json",
        sha256=hashlib.sha256(payload).hexdigest(),
        seed_count=seeds,
        token_count=len(reference_tokens()),
        metadata={"method": method},
        size_bytes=len(payload),
    )


@dataclass
class World:
    """A running app on a fresh database, with one approved team, one admin and one open phase."""

    settings: Settings
    client: TestClient
    factory: sessionmaker[Session]
    queued: list[int]
    team_id: int
    team_token: str
    admin_token: str
    phase: str
    extra_tokens: dict[str, str] = field(default_factory=dict)

    def team_headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.team_token}"}

    def admin_headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.admin_token}"}

    def session(self) -> Session:
        return self.factory()


def add_team(
    factory: sessionmaker[Session], name: str, approval: Approval = Approval.approved
) -> tuple[int, str]:
    """Create a team with one token; return its id and the token secret."""
    with transaction(factory) as session:
        team = create_team(session, name, [f"{name} member"], f"{name} lab", approval)
        _, secret = create_token(session, Scope.team, team, "test")
        return team.id, secret


def add_phase(
    factory: sessionmaker[Session],
    name: str,
    split: str = "reference",
    public_tokens: list[str] | None = None,
    opens_at: datetime | None = None,
    closes_at: datetime | None = None,
    **quotas: int | None,
) -> None:
    """Create a phase (and its split row when missing)."""
    with transaction(factory) as session:
        split_obj = session.query(Split).filter_by(name=split).one_or_none() or split_row(
            session, split, public_tokens
        )
        create_phase(session, name, split_obj, opens_at or utc_now() - timedelta(days=1), closes_at, **quotas)


@pytest.fixture(scope="session")
def migrated_sqlite(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An SQLite database file at the head revision, copied by every test that needs one."""
    path = tmp_path_factory.mktemp("template") / "template.sqlite"
    upgrade(f"sqlite:///{path}")
    return path


@pytest.fixture
def server_settings(tmp_path: Path, migrated_sqlite: Path) -> Settings:
    """Settings of a fresh migrated SQLite database under tmp_path."""
    shutil.copy(migrated_sqlite, tmp_path / "db.sqlite")
    return Settings(
        data_dir=tmp_path,
        database_url=f"sqlite:///{tmp_path / 'db.sqlite'}",
        broker_url=f"sqla+sqlite:///{tmp_path / 'broker.sqlite'}",
        bootstrap_samples=500,
        leaderboard_cache_seconds=0,
        splits={},
    )


@pytest.fixture
def world(server_settings: Settings) -> Iterator[World]:
    """The app with an approved team "alpha", an admin token and an open phase "test" on the reference split."""
    queued: list[int] = []
    app = create_app(server_settings, enqueue=queued.append)
    factory = app.state.session_factory
    team_id, team_token = add_team(factory, "alpha")
    with transaction(factory) as session:
        _, admin_token = create_token(session, Scope.admin, None, "test admin")
    add_phase(factory, "test")
    with TestClient(app) as client:
        yield World(server_settings, client, factory, queued, team_id, team_token, admin_token, "test")
    app.state.engine.dispose()


@pytest.fixture
def postgres_url() -> Iterator[str]:
    """A fresh, empty PostgreSQL database on the CI server, dropped afterwards."""
    with fresh_postgres_database() as url:
        yield url


@contextmanager
def fresh_postgres_database() -> Iterator[str]:
    """Create a uniquely named, empty PostgreSQL database on the CI server; yield its URL; drop it afterwards."""
    server = create_engine(POSTGRES_URL)
    try:
        with server.connect():
            pass
    except Exception as error:  # noqa: BLE001 - a missing server is a failure of a services test, said plainly
        pytest.fail(f"PostgreSQL at {POSTGRES_URL} is not usable: {error}")
    finally:
        server.dispose()
    with scratch_postgres_database(POSTGRES_URL, "navsim_lb_test") as url:
        yield url


def factory_for(url: str) -> sessionmaker[Session]:
    """Return a session factory on a database URL (migrated by the caller)."""
    return make_session_factory(make_engine(url))


def team_row(session: Session, team_id: int) -> Team:
    """Return a team row."""
    team = session.get(Team, team_id)
    assert team is not None
    return team


def phase_row(session: Session, name: str) -> Phase:
    """Return a phase row."""
    return session.query(Phase).filter_by(name=name).one()


def token_results(scores: dict[str, float | None], seed: int = 0) -> list[object]:
    """Return scorer TokenResults with the given PDMS per token (None: the token could not be scored).

    Subscores are set to the PDMS too, so a subscore mean equals the PDMS mean."""
    from scorer.evaluate import TokenResult

    return [
        TokenResult(token, seed, True, dict.fromkeys(ALL_RESULT_COLUMNS, score))
        if score is not None
        else TokenResult(token, seed, False, {}, "poses: non-finite value")
        for token, score in scores.items()
    ]


def score_run(
    factory: sessionmaker[Session],
    submission_id: int,
    per_seed: list[dict[str, float | None]],
    versions: tuple[str, ...] = LOG_REPLAY_VERSIONS,
    chunk: int = 16,
) -> None:
    """Play a worker: claim, write every (version, seed) in chunks through the services, then mark scored."""
    from server.runs import claim_submission, mark_scored, write_chunk_results

    with transaction(factory) as session:
        run = claim_submission(session, submission_id, "test-worker")
    assert run is not None
    for version in versions:
        for seed, scores in enumerate(per_seed):
            results = token_results(scores, seed)
            for start in range(0, len(results), chunk):
                with transaction(factory) as session:
                    assert write_chunk_results(
                        session,
                        submission_id,
                        run,
                        version,
                        results[start : start + chunk],
                        "test-worker",
                        0.5,
                    )
    with transaction(factory) as session:
        assert mark_scored(session, submission_id, run, "test-engine", 300)


def claimed_submission(world: World, payload: bytes) -> Submission:
    """Create a submission through the services and claim it as a worker would (status running, run 1)."""
    from server.runs import claim_submission
    from server.services.submissions import create_submission

    with transaction(world.factory) as session:
        team, phase = team_row(session, world.team_id), phase_row(session, "test")
        submission, _ = create_submission(
            session, team, phase, upload_of(payload), world.settings.submission_store
        )
        assert claim_submission(session, submission.id, "test-worker") == 1
        return submission


def submit_scored(
    world: World,
    team_id: int,
    payload: bytes,
    per_seed: list[dict[str, float | None]],
    method: str = "m",
    phase: str = "test",
    now: datetime | None = None,
) -> int:
    """Create a submission through the services and score it; return its id."""
    from server.services.submissions import create_submission

    with transaction(world.factory) as session:
        submission, _ = create_submission(
            session,
            team_row(session, team_id),
            phase_row(session, phase),
            upload_of(payload, seeds=len(per_seed), method=method),
            world.settings.submission_store,
            now=now,
        )
        submission_id = submission.id
    score_run(world.factory, submission_id, per_seed)
    return submission_id


def uniform(score: float | None, tokens: list[str] | None = None) -> dict[str, float | None]:
    """Return the same PDMS for every reference token."""
    return dict.fromkeys(tokens or reference_tokens(), score)
