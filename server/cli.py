"""Server subcommands of `navsim-lb`: db upgrade|downgrade|current, serve, admin helpers."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from navsim_lb.terminal import console, fail

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

# The server's modules are imported inside the commands: `navsim-lb score` should not pay for SQLAlchemy,
# Alembic and FastAPI at start-up.

db_app = typer.Typer(help="Database migrations (Alembic).", no_args_is_help=True)
admin_app = typer.Typer(
    help="Administration from the server machine (no API token needed).", no_args_is_help=True
)


def _timestamp(text: str | None) -> datetime | None:
    """Parse an ISO 8601 time; without a zone it is UTC."""
    if text is None:
        return None
    value = datetime.fromisoformat(text)
    return value if value.tzinfo else value.replace(tzinfo=UTC)


@db_app.command()
def upgrade(revision: Annotated[str, typer.Argument(help="target revision")] = "head") -> None:
    """Migrate the database (DATABASE_URL) up to the newest revision."""
    from server.migrate import upgrade as run_upgrade
    from server.settings import get_settings

    url = get_settings().database_url
    run_upgrade(url, revision)
    console.print(f"database migrated to {revision}")


@db_app.command()
def downgrade(
    revision: Annotated[str, typer.Argument(help='target revision; "base" drops every table')] = "-1",
) -> None:
    """Migrate the database down (one revision by default)."""
    from server.migrate import downgrade as run_downgrade
    from server.settings import get_settings

    run_downgrade(get_settings().database_url, revision)
    console.print(f"database migrated down to {revision}")


@db_app.command()
def current() -> None:
    """Print the database's revision and the newest one."""
    from server.db import make_engine
    from server.migrate import current_revision, head_revision
    from server.settings import get_settings

    engine = make_engine(get_settings().database_url)
    print(f"current: {current_revision(engine) or 'none'}\nhead: {head_revision()}")


def serve(
    host: Annotated[str, typer.Option(help="interface to listen on")] = "127.0.0.1",
    port: Annotated[int, typer.Option(envvar="PORT", help="TCP port")] = 8000,
    workers: Annotated[int, typer.Option(help="API processes")] = 1,
) -> None:
    """Run the API and web pages (uvicorn); refuses an un-migrated database."""
    import uvicorn

    from server.db import make_engine
    from server.migrate import NotMigratedError, require_migrated
    from server.settings import get_settings

    try:
        require_migrated(make_engine(get_settings().database_url))
    except NotMigratedError as error:
        raise fail(str(error)) from None
    uvicorn.run("server.main:app_from_environment", factory=True, host=host, port=port, workers=workers)


@admin_app.command("create-team")
def create_team_command(
    name: Annotated[str, typer.Argument(help="team name")],
    member: Annotated[list[str] | None, typer.Option(help="a member (repeatable)")] = None,
    affiliation: Annotated[str, typer.Option()] = "",
    pending: Annotated[bool, typer.Option(help="leave it for approval instead of approving it")] = False,
) -> None:
    """Create a team (approved unless --pending) and print its id."""
    from server.models import Approval
    from server.services.admin import add_team

    approval = Approval.pending if pending else Approval.approved
    with _session() as session:
        team_id = add_team(session, None, name, member or [], affiliation, approval).id
    print(team_id)


@admin_app.command("create-token")
def create_token_command(
    team: Annotated[str | None, typer.Option(help="team name (a team token)")] = None,
    admin: Annotated[bool, typer.Option("--admin", help="an admin token")] = False,
    name: Annotated[str, typer.Option(help="label of the token")] = "",
    expires_days: Annotated[float | None, typer.Option(help="lifetime in days (default: no expiry)")] = None,
) -> None:
    """Create a team or admin token and print its secret (shown once) on stdout."""
    from server.services.admin import issue_token
    from server.services.teams import team_by_name

    if admin == (team is not None):
        raise fail("give exactly one of --team NAME or --admin")
    expires_at = datetime.now(UTC) + timedelta(days=expires_days) if expires_days is not None else None
    with _session() as session:
        owner = team_by_name(session, team) if team is not None else None
        _, secret = issue_token(session, None, owner, name, expires_at)
    print(secret)


@admin_app.command("register-split")
def register_split_command(
    name: Annotated[str, typer.Argument(help="split name, e.g. private_test_e2e")],
    directory: Annotated[
        str,
        typer.Argument(
            help="split directory, or s3://bucket/prefix of an object store (holds scenes/, and two_stage.json "
            "for a two-stage split)"
        ),
    ],
    public_tokens: Annotated[
        Path | None, typer.Option(help="file with one public token per line; the rest is private")
    ] = None,
    baselines: Annotated[bool, typer.Option(help="queue the constant-velocity and human baselines")] = True,
    scenes_public: Annotated[
        bool,
        typer.Option(help="let teams see its scenes in drill-down pictures (never for a hidden test split)"),
    ] = False,
) -> None:
    """Register a split and queue its baseline submissions."""
    from server.queue import enqueue_submission
    from server.services.admin import add_split
    from server.settings import get_settings

    public = public_tokens.read_text().split() if public_tokens is not None else None
    settings = get_settings()
    with _session() as session:
        baselines_to = settings.submission_store if baselines else None
        split, added = add_split(session, None, name, directory, public, scenes_public, baselines_to)
        queued = [submission.id for submission in added]
        summary = (
            f"registered split {name}: {split.token_count} tokens, content hash {split.content_hash[:12]}…"
        )
    for submission_id in queued:
        enqueue_submission(submission_id, settings)
    console.print(summary + (f"; baselines queued as submissions {queued}" if queued else ""))


@admin_app.command("create-phase")
def create_phase_command(
    name: Annotated[str, typer.Argument(help="phase name, e.g. warmup")],
    split: Annotated[str, typer.Option(help="registered split name")],
    opens: Annotated[
        str | None, typer.Option(help="ISO 8601 opening time (default now; UTC if no zone)")
    ] = None,
    closes: Annotated[str | None, typer.Option(help="ISO 8601 closing time (default never)")] = None,
    per_day: Annotated[int | None, typer.Option(help="submissions per team per UTC day")] = None,
    total: Annotated[int | None, typer.Option(help="submissions per team in the phase")] = None,
    in_flight: Annotated[int | None, typer.Option(help="queued or running submissions per team")] = None,
) -> None:
    """Create a phase on a registered split."""
    from server.services.admin import add_phase

    with _session() as session:
        phase = add_phase(
            session, None, name, split, _timestamp(opens), _timestamp(closes), per_day, total, in_flight
        )
        console.print(f"phase {phase.name} on {split} opens {phase.opens_at.isoformat()}")


@admin_app.command("check-integrity")
def check_integrity_command(
    split: Annotated[str, typer.Argument(help="registered split name")],
) -> None:
    """Check a split's entries for a leaked log, copies between teams and probing; print each flag with its
    evidence on stdout, one JSON object a line (the admin console's integrity page shows the same). Nothing is
    hidden or disqualified: the organiser decides."""
    import json

    from server.numbers import counted
    from server.services.integrity import complete_check, integrity_report, start_check
    from server.services.splits import split_by_name
    from server.settings import get_settings

    with _session() as session:
        check = start_check(session, None, split_by_name(session, split))
        complete_check(session, get_settings(), check)
        if check.error is not None:
            raise fail(f"the check failed: {check.error}")
        (report,) = (c for c in integrity_report(session)["checks"] if c["id"] == check.id)
    for flag in report["flags"]:
        print(json.dumps(flag))
    skipped = f", {len(report['skipped'])} unreadable" if report["skipped"] else ""
    found = f"{counted(report['entries'], 'entry', 'entries')} read{skipped}; {counted(len(report['flags']), 'flag')}"
    console.print(f"split {split}: {found}")


@contextmanager
def _session() -> Iterator[Session]:
    """Yield a transaction on the configured, migrated database; service errors become CLI errors."""
    from server.db import make_engine, make_session_factory, transaction
    from server.migrate import NotMigratedError, require_migrated
    from server.services.errors import ServiceError
    from server.settings import get_settings

    engine = make_engine(get_settings().database_url)
    try:
        require_migrated(engine)
        with transaction(make_session_factory(engine)) as session:
            yield session
    except (NotMigratedError, ServiceError) as error:
        raise fail(str(error)) from None
    finally:
        engine.dispose()


def register(app: typer.Typer) -> None:
    """Add the server's subcommands to `app`: db, serve, admin."""
    app.add_typer(db_app, name="db")
    app.command()(serve)
    app.add_typer(admin_app, name="admin")
