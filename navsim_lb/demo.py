"""`navsim-lb demo` (`make demo`): the whole service on one machine, with nothing to install but the venv.

Migrates the configured database (an SQLite file under .navsim-lb by default), synthesises a demo split
if there is none, registers it with its two baselines, and beside it a small two-stage split (the 36 public
scenes of the repository's two-stage excerpt, tests/fixtures/epdms-two-stage-reactive: 3 groups of NAVSIM's
navhard-style mapping) with its phase and baselines, starts one worker (a consumer per core and the reaper of
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
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from navsim_lb.terminal import console, escape, fail, progress_bar
from scorer.versions import DEFAULT_VERSION

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from server.object_store import ObjectStore

# The server's modules, SQLAlchemy and httpx are imported where they are used: every `navsim-lb` command
# imports this module to register `demo`, and none of the others should pay for them.

SPLIT = "demo"
PHASE = "demo"
TWO_STAGE = "demo-two-stage"  # split and phase
TWO_STAGE_SOURCE = Path(__file__).resolve().parent.parent / "tests" / "fixtures" / "epdms-two-stage-reactive"
TEAM = "demo-team"
DEMO_METHODS = {False: "Noisy human (demo)", True: "Noisy human, two stages (demo)"}  # by split kind
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


def _two_stage_split_dir(data_dir: Path) -> Path | None:
    """Return the two-stage demo split directory, copied from the repository's excerpt on first use; None
    where the excerpt is not there (an installed package without the repository's tests)."""
    import shutil

    directory = data_dir / "splits" / TWO_STAGE
    if not (directory / "scenes").is_dir():
        if not TWO_STAGE_SOURCE.is_dir():
            return None
        directory.mkdir(parents=True, exist_ok=True)
        shutil.copytree(TWO_STAGE_SOURCE / "scenes", directory / "scenes")
        shutil.copy(TWO_STAGE_SOURCE / "two_stage.json", directory / "two_stage.json")
    return directory


def _warm_cache(split_dir: Path, cache_dir: Path, scenes: int, versions: Sequence[str]) -> None:
    """Build the split's metric caches under `versions` on every core, as an operator would beforehand."""
    from scorer.evaluate import build_split_cache

    with progress_bar(f"building the metric cache of {split_dir.name}", scenes) as advance:
        failures = build_split_cache(
            split_dir, cache_dir, list(versions), workers=os.cpu_count() or 1, progress=advance
        )
    if failures:
        raise fail(f"{len(failures)} demo scenes cannot be cached, e.g. {next(iter(failures.items()))}")


def _set_up(
    factory: sessionmaker[Session], split_dir: Path, two_stage_dir: Path | None, store: ObjectStore
) -> tuple[list[int], dict[str, str]]:
    """Register the splits, their baselines and phases and the team if missing; return the baselines to queue
    and new tokens. The two-stage phase opens just before the one-stage one, which stays the default."""
    from datetime import timedelta

    from sqlalchemy import select

    from server.db import transaction
    from server.models import Approval, Phase, Scope, Split, Team
    from server.services.admin import add_split
    from server.services.splits import create_phase
    from server.services.teams import create_team
    from server.services.tokens import create_token

    with transaction(factory) as session:
        queued = []
        for name, directory in ((SPLIT, split_dir), (TWO_STAGE, two_stage_dir)):
            if directory is None:
                continue
            split = session.scalar(select(Split).where(Split.name == name))
            if split is None:
                # Synthetic or public scenes: teams may see them in the drill-down pictures.
                split, baselines = add_split(session, None, name, directory, None, True, store)
                queued += [submission.id for submission in baselines]
            if session.scalar(select(Phase.id).where(Phase.name == name)) is None:
                default = session.scalar(select(Phase).where(Phase.name == PHASE))
                opens_at = default.opens_at - timedelta(minutes=1) if default is not None else None
                create_phase(session, name, split, opens_at=opens_at)
        team = session.scalar(select(Team).where(Team.name == TEAM)) or create_team(
            session, TEAM, ["Demo Member"], "Demo Lab", Approval.approved
        )
        # Secrets are never stored, so each run makes fresh tokens.
        _, team_token = create_token(session, Scope.team, team, "demo")
        _, admin_token = create_token(session, Scope.admin, None, "demo admin")
    return queued, {"team": team_token, "admin": admin_token}


def _demo_entry(split_dir: Path, out: Path, two_stage: bool = False) -> Path:
    """Write the demo entry of a split (in its form, one-stage or two-stage): the human trajectories with
    seeded noise (a plausible, imperfect method)."""

    import numpy as np

    from scorer.baselines import baseline_submission, two_stage_baseline_submission
    from scorer.geometry import FloatArray
    from scorer.submission import Submission as Predictions
    from scorer.submission import TwoStageSubmission, dump_submission_json, dump_two_stage_submission_json

    rng = np.random.default_rng(NOISE_SEED)
    scale = np.array([NOISE_XY_M, NOISE_XY_M, NOISE_HEADING_RAD])

    def noisy(seed: dict[str, FloatArray]) -> dict[str, FloatArray]:
        return {token: poses + rng.normal(0.0, scale, poses.shape) for token, poses in seed.items()}

    method = DEMO_METHODS[two_stage]
    if two_stage:
        stages = two_stage_baseline_submission(split_dir, "human", method)
        metadata = stages.metadata._replace(team_name=TEAM, authors="Demo Member", institution="Demo Lab")
        entry = TwoStageSubmission(
            metadata, (noisy(stages.first_stage[0]),), (noisy(stages.second_stage[0]),)
        )
        out.write_bytes(dump_two_stage_submission_json(entry))
        return out
    human = baseline_submission(split_dir, "human", method)
    metadata = human.metadata._replace(team_name=TEAM, authors="Demo Member", institution="Demo Lab")
    out.write_bytes(dump_submission_json(Predictions(metadata, (noisy(human.seeds[0]),))))
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


def _states(factory: sessionmaker[Session]) -> dict[int, tuple[str, str, str | None]]:
    """Return submission id -> (method, status, its score on all tokens under the default version, or the
    two-stage version on a two-stage split) of every submission."""
    from sqlalchemy import select

    from scorer.versions import TWO_STAGE_VERSIONS, get_version
    from server.models import Submission, Summary
    from server.numbers import percent

    with factory() as session:
        rows = session.execute(
            select(Submission.id, Submission.method, Submission.status, Summary.metric_version, Summary.score)
            .outerjoin(
                Summary,
                (Summary.submission_id == Submission.id)
                & Summary.metric_version.in_((DEFAULT_VERSION, *TWO_STAGE_VERSIONS))
                & (Summary.subset == "all"),
            )
            .order_by(Submission.id)
        ).all()
    return {
        row.id: (
            row.method,
            row.status,
            None
            if row.score is None
            else f"{get_version(row.metric_version).score_label} ({row.metric_version}) {percent(row.score)} %",
        )
        for row in rows
    }


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
                result = score if score is not None else status
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
    from scorer.versions import LOG_REPLAY_VERSIONS, TWO_STAGE_VERSIONS
    from server.db import make_engine, make_session_factory
    from server.migrate import upgrade
    from server.models import Phase, Status, Submission, Team
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
    _warm_cache(split_dir, settings.cache_dir, scene_count, LOG_REPLAY_VERSIONS)
    two_stage_dir = _two_stage_split_dir(data_dir)
    if two_stage_dir is None:
        console.print(f"no two-stage demo split: {TWO_STAGE_SOURCE} is not there")
    else:
        scene_count = len(list((two_stage_dir / "scenes").iterdir()))
        _warm_cache(two_stage_dir, settings.cache_dir, scene_count, TWO_STAGE_VERSIONS)
    engine = make_engine(settings.database_url)
    factory = make_session_factory(engine)
    queued, tokens = _set_up(factory, split_dir, two_stage_dir, settings.submission_store)
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
            phases = [(PHASE, split_dir, False)] + (
                [(TWO_STAGE, two_stage_dir, True)] if two_stage_dir else []
            )
            for phase, directory, two_stage in phases:
                with factory() as session:
                    entered = session.scalar(
                        select(Submission.id)
                        .join(Team)
                        .join(Phase)
                        .where(Team.name == TEAM, Phase.name == phase, Submission.status != Status.failed)
                    )
                if entered is not None:
                    continue
                entry = _demo_entry(directory, data_dir / f"{phase}-submission.json", two_stage)
                with httpx.Client(
                    base_url=url, headers={"Authorization": f"Bearer {tokens['team']}"}
                ) as client:
                    accepted = upload(client, entry, {"method": DEMO_METHODS[two_stage], "phase": phase})
                console.print(f"demo entry of phase {phase} submitted as submission {accepted['id']}")
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
