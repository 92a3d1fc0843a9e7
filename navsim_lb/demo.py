"""`navsim-lb demo` (`make demo`): the whole service on one machine, with nothing to install but the venv.

Migrates the configured database (an SQLite file under .navsim-lb by default), synthesises a demo split
if there is none, registers it with its two baselines, starts one worker (a consumer per core and the reaper of
lost work: worker.supervisor) on the configured broker (the embedded SQLite one by default), started again if a
signal kills it, and the API, creates a demo team and an
admin with their tokens in `.navsim-lb/demo-tokens.json`, submits a demo entry through the API, prints
the leaderboard URL and runs until Ctrl-C; then it stops every process it started.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape

from navsim_lb.terminal import console, fail, progress_bar
from scorer.versions import DEFAULT_VERSION

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from server.object_store import ObjectStore

# The server's modules, SQLAlchemy and httpx are imported where they are used: every `navsim-lb` command
# imports this module to register `demo`, and none of the others should pay for them.

SPLIT = "demo"
PHASE = "demo"
TEAM = "demo-team"
SPLIT_SEED = 0
NOISE_SEED = 7
NOISE_XY_M = 0.3  # standard deviation of the demo entry's noise on the human trajectory
NOISE_HEADING_RAD = 0.03
STARTUP_TIMEOUT_S = 60.0


def _split_dir(data_dir: Path, scenes: int) -> Path:
    """Return the demo split directory, synthesising it on first use."""
    from scorer.synth import synthesize_split

    directory = data_dir / "splits" / SPLIT
    if not (directory / "scenes").is_dir():
        with progress_bar("synthesising the demo split", scenes) as advance:
            synthesize_split(directory, scenes, SPLIT_SEED, progress=advance)
    return directory


def _warm_cache(split_dir: Path, cache_dir: Path, scenes: int) -> None:
    """Build the split's metric caches (v1.0, v1.1, v2.2) on every core, as an operator would beforehand."""
    from scorer.evaluate import build_split_cache
    from scorer.versions import LOG_REPLAY_VERSIONS

    with progress_bar("building the metric cache", scenes) as advance:
        failures = build_split_cache(
            split_dir, cache_dir, list(LOG_REPLAY_VERSIONS), workers=os.cpu_count() or 1, progress=advance
        )
    if failures:
        raise fail(f"{len(failures)} demo scenes cannot be cached, e.g. {next(iter(failures.items()))}")


def _set_up(
    factory: sessionmaker[Session], split_dir: Path, store: ObjectStore
) -> tuple[list[int], dict[str, str]]:
    """Register split, baselines, phase and team if missing; return the baselines to queue and new tokens."""
    from sqlalchemy import select

    from server.db import transaction
    from server.models import Approval, Phase, Scope, Split, Team
    from server.services.admin import add_split
    from server.services.splits import create_phase
    from server.services.teams import create_team
    from server.services.tokens import create_token

    with transaction(factory) as session:
        split = session.scalar(select(Split).where(Split.name == SPLIT))
        queued = []
        if split is None:
            # Synthetic scenes: teams may see them in the drill-down pictures.
            split, baselines = add_split(session, None, SPLIT, split_dir, None, True, store)
            queued = [submission.id for submission in baselines]
        if session.scalar(select(Phase.id).where(Phase.name == PHASE)) is None:
            create_phase(session, PHASE, split)
        team = session.scalar(select(Team).where(Team.name == TEAM)) or create_team(
            session, TEAM, ["Demo Member"], "Demo Lab", Approval.approved
        )
        # Secrets are never stored, so each run makes fresh tokens.
        _, team_token = create_token(session, Scope.team, team, "demo")
        _, admin_token = create_token(session, Scope.admin, None, "demo admin")
    return queued, {"team": team_token, "admin": admin_token}


def _demo_entry(split_dir: Path, out: Path) -> Path:
    """Write the demo entry: the human trajectories with seeded noise (a plausible, imperfect method)."""
    from dataclasses import replace

    import numpy as np

    from scorer.baselines import baseline_submission
    from scorer.geometry import FloatArray
    from scorer.submission import Submission as Predictions
    from scorer.submission import dump_submission_json

    human = baseline_submission(split_dir, "human", "Noisy human (demo)")
    rng = np.random.default_rng(NOISE_SEED)
    scale = np.array([NOISE_XY_M, NOISE_XY_M, NOISE_HEADING_RAD])
    noisy: dict[str, FloatArray] = {
        token: poses + rng.normal(0.0, scale, poses.shape) for token, poses in human.seeds[0].items()
    }
    metadata = replace(human.metadata, team_name=TEAM, authors="Demo Member", institution="Demo Lab")
    out.write_bytes(dump_submission_json(Predictions(metadata, (noisy,))))
    return out


def _check_alive(children: dict[str, subprocess.Popen[bytes]], logs: Path) -> None:
    for name, process in children.items():
        if process.poll() is not None:
            raise fail(f"the {name} stopped (exit code {process.returncode}); see {logs / f'{name}.log'}")


def _wait_for_api(url: str, children: dict[str, subprocess.Popen[bytes]], logs: Path) -> None:
    import httpx

    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while time.monotonic() < deadline:
        _check_alive(children, logs)
        try:
            if httpx.get(f"{url}/api/v1/health", timeout=2.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    raise fail(f"the API did not answer on {url} within {STARTUP_TIMEOUT_S:.0f} s; see {logs / 'api.log'}")


def _states(factory: sessionmaker[Session]) -> dict[int, tuple[str, str, float | None]]:
    """Return submission id -> (method, status, PDMS of the default version on all tokens) of every submission."""
    from sqlalchemy import select

    from server.models import Submission, Summary

    with factory() as session:
        rows = session.execute(
            select(Submission.id, Submission.method, Submission.status, Summary.score)
            .outerjoin(
                Summary,
                (Summary.submission_id == Submission.id)
                & (Summary.metric_version == DEFAULT_VERSION)
                & (Summary.subset == "all"),
            )
            .order_by(Submission.id)
        ).all()
    return {row.id: (row.method, row.status, row.score) for row in rows}


def _watch(
    factory: sessionmaker[Session],
    children: dict[str, subprocess.Popen[bytes]],
    logs: Path,
    until_scored: bool,
    restart_killed_worker: Callable[[], None],
) -> bool:
    """Report submissions as they finish; with `until_scored`, return, once none is active, if all scored."""
    from server.models import ACTIVE_STATUSES, Status

    reported: dict[int, str] = {}
    while True:
        restart_killed_worker()
        _check_alive(children, logs)
        states = _states(factory)
        for submission_id, (method, status, score) in states.items():
            if reported.get(submission_id) != status and status not in ACTIVE_STATUSES:
                result = f"PDMS ({DEFAULT_VERSION}) {score:.4f}" if score is not None else status
                console.print(escape(f"submission {submission_id} ({method}): {result}"))
            reported[submission_id] = status
        if until_scored and all(status not in ACTIVE_STATUSES for _, status, _ in states.values()):
            return all(status == Status.scored for _, status, _ in states.values())
        time.sleep(1.0)


def demo(
    port: Annotated[int, typer.Option(envvar="PORT", help="TCP port of the API and web pages")] = 8000,
    host: Annotated[str, typer.Option(help="interface to listen on")] = "127.0.0.1",
    scenes: Annotated[
        int, typer.Option(help="scenes of the synthetic demo split (when it does not exist)")
    ] = 200,
    concurrency: Annotated[int, typer.Option(help="scoring processes of the worker")] = os.cpu_count() or 1,
    exit_when_scored: Annotated[
        bool, typer.Option("--exit-when-scored", help="stop everything once every submission is scored")
    ] = False,
) -> None:
    """Run the whole leaderboard locally: database, demo split, worker, API, demo team; Ctrl-C stops it."""
    import httpx
    from sqlalchemy import select

    from navsim_lb.client import upload
    from navsim_lb.processes import api_command, child_process
    from server.db import make_engine, make_session_factory
    from server.migrate import upgrade
    from server.models import Status, Submission, Team
    from server.queue import enqueue_submission
    from server.settings import get_settings
    from worker.cli import worker_command

    settings = get_settings()
    data_dir = settings.data_dir.resolve()
    logs = data_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    upgrade(settings.database_url)
    split_dir = _split_dir(data_dir, scenes)
    scene_count = len(list((split_dir / "scenes").iterdir()))
    _warm_cache(split_dir, settings.cache_dir, scene_count)
    engine = make_engine(settings.database_url)
    factory = make_session_factory(engine)
    queued, tokens = _set_up(factory, split_dir, settings.submission_store)
    tokens_file = data_dir / "demo-tokens.json"
    tokens_file.write_text(json.dumps(tokens, indent=1) + "\n")
    tokens_file.chmod(0o600)
    for submission_id in queued:  # they wait in the broker until the worker is up
        enqueue_submission(submission_id, settings)

    env = {**os.environ, "DATA_DIR": str(data_dir)}  # the children derive the same paths from it
    url = f"http://{host}:{port}"
    # SIGTERM (a service manager, a test) stops the children as Ctrl-C does.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    worker = worker_command(concurrency, reaper=True)
    try:
        with ExitStack() as stack:
            children = {
                "worker": stack.enter_context(child_process(worker, env, logs / "worker.log")),
                "api": stack.enter_context(child_process(api_command(host, port), env, logs / "api.log")),
            }

            def restart_killed_worker() -> None:
                # A worker that failed by itself stops the demo (_check_alive); one a signal killed (SIGKILL,
                # the out-of-memory killer) is started again: its consumers stop with it (worker.supervised),
                # and the reaper sends again what they held.
                returncode = children["worker"].poll()
                if returncode is not None and returncode < 0:
                    console.print(f"the worker was killed (signal {-returncode}); starting it again")
                    children["worker"] = stack.enter_context(child_process(worker, env, logs / "worker.log"))

            _wait_for_api(url, children, logs)
            with factory() as session:
                entered = session.scalar(
                    select(Submission.id)
                    .join(Team)
                    .where(Team.name == TEAM, Submission.status != Status.failed)
                )
            if entered is None:
                entry = _demo_entry(split_dir, data_dir / "demo-submission.json")
                with httpx.Client(
                    base_url=url, headers={"Authorization": f"Bearer {tokens['team']}"}
                ) as client:
                    accepted = upload(client, entry, {"method": "Noisy human (demo)"})
                console.print(f"demo entry submitted as submission {accepted['id']}")
            console.print(
                f"\n[bold]leaderboard: {url}/[/bold]   API docs: {url}/docs   admin: {url}/admin\n"
                f"tokens (team, admin): {tokens_file}   logs: {logs}\n"
                + ("" if exit_when_scored else "press Ctrl-C to stop\n")
            )
            all_scored = _watch(factory, children, logs, exit_when_scored, restart_killed_worker)
            console.print("stopping the worker and the API")
    except KeyboardInterrupt:
        console.print("stopped")
        return
    finally:
        engine.dispose()
    if not all_scored:
        raise fail("some submissions failed; see the leaderboard's admin page and the worker log")


def register(app: typer.Typer) -> None:
    """Add `demo` to `app`."""
    app.command()(demo)
