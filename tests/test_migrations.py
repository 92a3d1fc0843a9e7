"""Alembic migrations: upgrade creates every table of the model, downgrade removes them, on SQLite and PostgreSQL;
the app refuses an un-migrated database with the command that fixes it."""

from __future__ import annotations

from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import inspect, text

from server.db import make_engine
from server.main import create_app
from server.migrate import NotMigratedError, current_revision, downgrade, head_revision, upgrade
from server.models import Base
from server.settings import Settings

MODEL_TABLES = set(Base.metadata.tables)


def _round_trip(url: str) -> None:
    engine = make_engine(url)
    try:
        assert current_revision(engine) is None
        upgrade(url)
        assert current_revision(engine) == head_revision()
        assert MODEL_TABLES <= set(inspect(engine).get_table_names())
        with engine.connect() as connection:
            # The migrations build exactly the model: no table, column, index or constraint differs.
            differences = compare_metadata(MigrationContext.configure(connection), Base.metadata)
        assert differences == []
        downgrade(url, "base")
        assert current_revision(engine) is None
        assert MODEL_TABLES.isdisjoint(inspect(engine).get_table_names())
        upgrade(url)
        assert MODEL_TABLES <= set(inspect(engine).get_table_names())
    finally:
        engine.dispose()


def test_upgrade_and_downgrade_on_sqlite(tmp_path: Path) -> None:
    _round_trip(f"sqlite:///{tmp_path / 'db.sqlite'}")


@pytest.mark.services
def test_upgrade_and_downgrade_on_postgresql(postgres_url: str) -> None:
    _round_trip(postgres_url)


def test_app_refuses_an_unmigrated_database(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, database_url=f"sqlite:///{tmp_path / 'db.sqlite'}")
    with pytest.raises(NotMigratedError, match="navsim-lb db upgrade"):
        create_app(settings, enqueue=lambda _: None)
    upgrade(settings.database_url, head_revision())
    app = create_app(settings, enqueue=lambda _: None)
    app.state.engine.dispose()


def _splits_keep_their_scenes_hidden_after_0002(url: str) -> None:
    engine = make_engine(url)
    try:
        upgrade(url, "0001_initial")
        with engine.begin() as connection:
            connection.execute(
                text(
                    "INSERT INTO splits (name, directory, content_hash, token_count, created_at) "
                    "VALUES ('test', '/x', 'h', 1, CURRENT_TIMESTAMP)"
                )
            )
        upgrade(url)
        with engine.connect() as connection:
            assert connection.execute(text("SELECT scenes_public FROM splits")).scalar_one() in (False, 0)
        downgrade(url, "0001_initial")
        assert "scenes_public" not in {column["name"] for column in inspect(engine).get_columns("splits")}
    finally:
        engine.dispose()


def test_a_split_registered_before_scene_policies_stays_hidden_on_sqlite(tmp_path: Path) -> None:
    _splits_keep_their_scenes_hidden_after_0002(f"sqlite:///{tmp_path / 'db.sqlite'}")


@pytest.mark.services
def test_a_split_registered_before_scene_policies_stays_hidden_on_postgresql(postgres_url: str) -> None:
    _splits_keep_their_scenes_hidden_after_0002(postgres_url)
