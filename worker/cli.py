"""`navsim-lb worker`: scoring consumers (and the reaper) on the configured broker (DATABASE_URL, BROKER_URL, ...)."""

from __future__ import annotations

import os
import sys
from typing import Annotated

import typer

from worker import SCORING_NICENESS

DEFAULT_APP = "worker.app"
DEFAULT_NAME = "navsim-lb"


def worker_command(
    concurrency: int,
    reaper: bool,
    loglevel: str = "info",
    app: str = DEFAULT_APP,
    name: str = DEFAULT_NAME,
    nice: int = SCORING_NICENESS,
) -> list[str]:
    """Return the command line of `navsim-lb worker` with these options, run by this interpreter."""
    command = [
        sys.executable,
        "-m",
        "worker",
        f"--concurrency={concurrency}",
        f"--loglevel={loglevel}",
        f"--app={app}",
        f"--name={name}",
        f"--nice={nice}",
    ]
    return command + (["--reaper"] if reaper else [])


def run_worker(
    concurrency: Annotated[
        int,
        typer.Option(
            "--concurrency", "-c", help="scoring processes (default: one per core); 0 with --reaper"
        ),
    ] = os.cpu_count() or 1,
    reaper: Annotated[
        bool, typer.Option("--reaper", help="also run the reaper of lost work (exactly one in a deployment)")
    ] = False,
    loglevel: Annotated[str, typer.Option(help="debug, info, warning or error")] = "info",
    app: Annotated[str, typer.Option(help="module of the workers' Celery app")] = DEFAULT_APP,
    name: Annotated[
        str, typer.Option(help="consumers are named NAME-1@host, NAME-2@host, ...")
    ] = DEFAULT_NAME,
    nice: Annotated[
        int,
        typer.Option(
            min=0,
            max=19,
            help="how much lower the scoring consumers run than the supervisor (Unix niceness): on a host"
            " shared with the API they yield the CPU to its requests; 0 keeps the same priority",
        ),
    ] = SCORING_NICENESS,
) -> None:
    """Score chunks of submissions (v1.0, v1.1, v2.2): one consumer process per core, each started again when
    it dies or outlasts its time limit."""
    from worker.supervisor import supervise

    if concurrency < 0 or (concurrency == 0 and not reaper):
        raise typer.BadParameter("run at least one consumer, or the reaper alone (--concurrency 0 --reaper)")
    raise typer.Exit(supervise(concurrency, reaper, app, name, loglevel, nice))


def register(app: typer.Typer) -> None:
    """Add `worker` to `app`."""
    app.command("worker")(run_worker)
