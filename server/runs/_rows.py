"""Writing a scored chunk: its per-token rows, its record finished, then the run's progress (server.runs._finish).

Rows are upserted on (submission, metric version, seed, token): a repeated chunk overwrites its rows, it
never doubles them, and a chunk of a run no longer wanted (cancelled, finished or re-run) writes nothing.

PostgreSQL gets one statement per call whose parameters are one array per column, sent in binary and
unnested by the server. psycopg's executemany sends one statement per row (a navtest-size chunk has 1152),
and the server's per-statement work was about two thirds of a chunk's write; text arrays would cost it
a float parse per value. SQLite, in process, takes executemany as it is.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from datetime import datetime
from functools import cache
from typing import Any

from sqlalchemy import update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from scorer.versions import ALL_RESULT_COLUMNS
from server.models import ChunkState, ScoringChunk, TokenResultRow, utc_now
from server.runs._aggregate import stored_value
from server.runs._finish import finish_if_complete
from server.runs._job import ChunkInputs
from server.runs._run import is_current, locked_submission
from server.runs._score import ScoredChunk

MAX_DETAIL_CHARS = 20000

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


def write_chunk_results(
    session: Session,
    submission_id: int,
    run: int,
    metric_version: str,
    results: Sequence[Any],
    worker: str,
    duration_s: float,
    now: datetime | None = None,
) -> bool:
    """Upsert one version's scorer TokenResults of a chunk (seed None counts as 0).

    Returns False, writing nothing, when the run is no longer wanted: the worker should then stop.
    """
    now = now or utc_now()
    submission = locked_submission(session, submission_id)
    if not is_current(submission, run):
        return False
    if results:
        share = duration_s / len(results)
        upsert_token_rows(
            session,
            [
                (
                    *(submission_id, metric_version, result.seed or 0, result.token),
                    *(result.valid, result.error, run, worker, share, now, result.detail or None),
                    *(
                        stored_value(result.metrics.get(column)) if result.valid else None
                        for column in ALL_RESULT_COLUMNS
                    ),
                )
                for result in results
            ],
        )
    return True


def finish_chunk(
    session: Session, chunk_id: int, state: ChunkState = ChunkState.done, now: datetime | None = None
) -> None:
    """Mark a chunk done (its rows are written) or failed (its token's process died: written as failed, and
    one more death on record)."""
    died = int(state == ChunkState.failed)
    session.execute(
        update(ScoringChunk)
        .where(ScoringChunk.id == chunk_id)
        .values(state=state, finished_at=now or utc_now(), deaths=ScoringChunk.deaths + died)
    )


def write_chunk(
    session: Session,
    inputs: ChunkInputs,
    scored: ScoredChunk,
    worker: str,
    engine_version: str,
    bootstrap_samples: int,
) -> str:
    """Write a chunk's rows and finish its record; aggregate the run if they were its last. Return what
    happened: "dropped" (the run is no longer wanted), "scored" (the run is), or how many tokens were written."""
    job = inputs.job
    for version, rows in scored.rows.items():
        if not write_chunk_results(
            session, job.submission_id, job.run, version, rows, worker, scored.seconds_per_version
        ):
            return "dropped"
    finish_chunk(
        session, inputs.chunk_id, ChunkState.done if inputs.process_death is None else ChunkState.failed
    )
    if scored.admin_note:
        submission = locked_submission(session, job.submission_id)
        notes = filter(None, [submission.error_detail, scored.admin_note])
        submission.error_detail = "\n".join(notes)[-MAX_DETAIL_CHARS:]
    if finish_if_complete(session, job.submission_id, job.run, engine_version, bootstrap_samples):
        return "scored"
    return f"{len(inputs.todo)} tokens"
