"""`navsim-lb worker`: run a Celery worker on the configured broker (DATABASE_URL, BROKER_URL, ...)."""

from __future__ import annotations

import os
import sys
from typing import Annotated

import typer


def worker_command(concurrency: int, beat: bool, loglevel: str = "info") -> list[str]:
    """Return the command line of a Celery worker process serving the configured queue."""
    command = [
        sys.executable,
        "-m",
        "celery",
        "--app=worker.app",
        "worker",
        f"--concurrency={concurrency}",
        f"--loglevel={loglevel}",
        # Gossip, mingle and heartbeats synchronise revokes and events, which nothing here uses.
        "--without-gossip",
        "--without-mingle",
        "--without-heartbeat",
    ]
    return command + (["--beat"] if beat else [])


def run_worker(
    concurrency: Annotated[
        int, typer.Option("--concurrency", "-c", help="scoring processes (default: one per core)")
    ] = os.cpu_count() or 1,
    beat: Annotated[
        bool, typer.Option("--beat", help="also run the periodic reaper of lost work (in exactly one worker)")
    ] = False,
    loglevel: Annotated[str, typer.Option(help="debug, info, warning or error")] = "info",
) -> None:
    """Run a scoring worker on the configured broker: chunks of submissions in v1.0, v1.1 and v2.2."""
    command = worker_command(concurrency, beat, loglevel)
    os.execv(command[0], command)


def register(app: typer.Typer) -> None:
    """Add `worker` to `app`."""
    app.command("worker")(run_worker)
