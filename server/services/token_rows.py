"""Upserting a chunk's per-token rows, keyed by (submission, metric version, seed, token): a repeated chunk
overwrites its rows, it never doubles them.

PostgreSQL gets one statement per call whose parameters are one array per column, sent in binary and
unnested by the server. psycopg's executemany sends one statement per row (a navtest-size chunk has 1152),
and the server's per-statement work was about two thirds of a chunk's write; text arrays would cost it
a float parse per value. SQLite, in process, takes executemany as it is.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from functools import cache
from typing import Any

from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from scorer.versions import ALL_RESULT_COLUMNS
from server.models import TokenResultRow

UPSERT_KEY = ("submission_id", "metric_version", "seed", "token")
# The values of a row, in this order.
WRITTEN_COLUMNS = (
    *UPSERT_KEY,
    *("valid", "error", "run", "worker", "duration_s", "scored_at", "detail"),
    *ALL_RESULT_COLUMNS,
)
_DETAIL = WRITTEN_COLUMNS.index("detail")


@cache
def _postgresql_upsert() -> str:
    """Return the statement inserting the rows of one array per column, overwriting those already there."""
    table = TokenResultRow.__table__
    dialect = postgresql.dialect()
    arrays = ", ".join(f"%b::{table.c[name].type.compile(dialect=dialect)}[]" for name in WRITTEN_COLUMNS)
    updates = ", ".join(f"{name} = excluded.{name}" for name in WRITTEN_COLUMNS if name not in UPSERT_KEY)
    return (
        f"INSERT INTO {TokenResultRow.__tablename__} ({', '.join(WRITTEN_COLUMNS)}) SELECT * FROM unnest({arrays}) "
        f"ON CONFLICT ({', '.join(UPSERT_KEY)}) DO UPDATE SET {updates}"
    )


def upsert_token_rows(session: Session, rows: Sequence[tuple[Any, ...]]) -> None:
    """Insert `rows`, each the values of WRITTEN_COLUMNS (`detail` a dict or None, timestamps in UTC), or
    overwrite the rows of the same key."""
    if not rows:
        return
    dialect = session.get_bind().dialect.name
    if dialect == "postgresql":
        columns = [list(column) for column in zip(*rows, strict=True)]
        columns[_DETAIL] = [None if detail is None else json.dumps(detail) for detail in columns[_DETAIL]]
        cursor = session.connection().connection.driver_connection.cursor()  # type: ignore[union-attr]
        cursor.execute(_postgresql_upsert(), columns)
    elif dialect == "sqlite":
        statement = sqlite.insert(TokenResultRow)
        updated = {name: statement.excluded[name] for name in WRITTEN_COLUMNS if name not in UPSERT_KEY}
        upsert = statement.on_conflict_do_update(index_elements=list(UPSERT_KEY), set_=updated)
        session.connection().execute(upsert, [dict(zip(WRITTEN_COLUMNS, row, strict=True)) for row in rows])
    else:
        raise NotImplementedError(f"per-token upsert is not implemented for {dialect}")
