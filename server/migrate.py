"""Alembic from Python: upgrade, downgrade, current revision, and the check the app runs at startup."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine

# Package data of `server.migrations`: the same lookup in a checkout and an installed wheel.
MIGRATIONS_DIR = Path(str(files("server.migrations")))


class NotMigratedError(RuntimeError):
    """The database schema is not at the head revision of the migrations."""


def alembic_config(database_url: str) -> Config:
    """Return an Alembic config for `database_url` using the project's migrations directory."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    # ConfigParser interpolation: a literal % in a URL (encoded password) must be doubled.
    config.set_main_option("sqlalchemy.url", database_url.replace("%", "%%"))
    return config


def upgrade(database_url: str, revision: str = "head") -> None:
    """Migrate the database up to `revision`."""
    command.upgrade(alembic_config(database_url), revision)


def downgrade(database_url: str, revision: str = "-1") -> None:
    """Migrate the database down to `revision` ("base" removes every table)."""
    command.downgrade(alembic_config(database_url), revision)


def head_revision() -> str:
    """Return the newest revision of the migrations directory."""
    head = ScriptDirectory(str(MIGRATIONS_DIR)).get_current_head()
    assert head is not None, f"no migration in {MIGRATIONS_DIR}"
    return head


def current_revision(engine: Engine) -> str | None:
    """Return the revision the database is at, or None when it was never migrated."""
    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def require_migrated(engine: Engine) -> None:
    """Raise NotMigratedError with the fix when the database is not at the head revision."""
    current, head = current_revision(engine), head_revision()
    if current != head:
        raise NotMigratedError(
            f"database {engine.url.render_as_string(hide_password=True)} is at revision {current or 'none'}, "
            f"the server needs {head}: run `navsim-lb db upgrade`"
        )
