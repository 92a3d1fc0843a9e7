"""`navsim-lb demo --exit-when-scored` end to end on a fresh directory: the embedded defaults, a worker and
the API as child processes, baselines and the demo entry scored, tokens written, every child stopped; and a
demo killed mid-run with all its processes (a power cut, a container killed), then started again, that
finishes every submission with every row once."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from contextlib import suppress
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker
from worker_testing import free_port, wait_for

from scorer.versions import LOG_REPLAY_VERSIONS
from server.db import make_engine, make_session_factory
from server.models import ChunkState, ScoringChunk, Status, Submission, TokenResultRow

NAVSIM_LB = str(Path(sys.executable).parent / "navsim-lb")
# Settings the demo must derive itself: a developer's own configuration must not leak into the test.
SETTINGS_VARIABLES = (
    "DATA_DIR",
    "DATABASE_URL",
    "BROKER_URL",
    "STORAGE_DIR",
    "CACHE_DIR",
    "SPLITS",
    "QUEUE_NAME",
)


def _processes_started_under(data_dir: Path) -> list[int]:
    """Return the pids of live processes whose environment points at `data_dir` (the demo's children)."""
    marker = f"DATA_DIR={data_dir.resolve()}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if marker in (entry / "environ").read_bytes().split(b"\0"):
                found.append(int(entry.name))
        except OSError:  # gone meanwhile, or not ours to read
            continue
    return found


def _demo_env() -> dict[str, str]:
    return {key: value for key, value in os.environ.items() if key not in SETTINGS_VARIABLES}


def _demo_until_scored(command: list[str], directory: Path, env: dict[str, str]) -> str:
    """Run the demo `command` with --exit-when-scored in `directory`; return what it said (stderr)."""
    done = subprocess.run(
        [*command, "--exit-when-scored"],
        cwd=directory,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return done.stderr


def test_demo_runs_end_to_end_and_stops_what_it_started(tmp_path: Path) -> None:
    said = _demo_until_scored(
        [NAVSIM_LB, "demo", "--scenes", "12", "--port", str(free_port())], tmp_path, _demo_env()
    )
    data_dir = tmp_path / ".navsim-lb"
    assert "leaderboard: http://" in said
    tokens = json.loads((data_dir / "demo-tokens.json").read_text())
    assert set(tokens) == {"team", "admin"} and all(secret.startswith("nlb_") for secret in tokens.values())

    engine = make_engine(f"sqlite:///{data_dir / 'navsim-lb.sqlite'}")
    with make_session_factory(engine)() as session:
        submissions = session.scalars(select(Submission).order_by(Submission.id)).all()
        states = [(s.split.name, s.is_baseline, s.status, s.method) for s in submissions]
    engine.dispose()
    # Beside the one-stage demo split, the two-stage one: baselines and an entry on each.
    assert states == [
        ("demo", True, Status.scored, "Constant Velocity"),
        ("demo", True, Status.scored, "Human"),
        ("demo-two-stage", True, Status.scored, "Constant Velocity"),
        ("demo-two-stage", True, Status.scored, "Human"),
        ("demo", False, Status.scored, "Noisy human (demo)"),
        ("demo-two-stage", False, Status.scored, "Noisy human, two stages (demo)"),
    ]
    assert _processes_started_under(data_dir) == []


RESTART_SCENES = 24


def _mid_run(factory: sessionmaker[Session]) -> bool:
    """Whether a chunk is being scored, some rows are written, and some submission is not scored yet."""
    with factory() as session:
        running = session.scalar(select(func.count()).where(ScoringChunk.state == ChunkState.running))
        rows = session.scalar(select(func.count()).select_from(TokenResultRow))
        unscored = session.scalar(select(func.count()).where(Submission.status != Status.scored))
    return bool(running and rows and unscored)


def test_a_demo_killed_mid_run_and_started_again_scores_every_submission_once(tmp_path: Path) -> None:
    """SIGKILL of the demo and every process it started while chunks are scored, then `navsim-lb demo` again:
    the new worker takes what waits in the broker, its reaper sends again what the dead one held."""
    data_dir = tmp_path / ".navsim-lb"
    command = [NAVSIM_LB, "demo", "--scenes", str(RESTART_SCENES), "--port", str(free_port())]
    env = _demo_env() | {"REAPER_INTERVAL": "2"}
    with (tmp_path / "first.log").open("wb") as log:
        first = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT)
    engine = None
    try:
        # Written once the database is migrated and the demo's split, phase and team are in it.
        wait_for((data_dir / "demo-tokens.json").exists, "the demo to be set up", timeout=300)
        engine = make_engine(f"sqlite:///{data_dir / 'navsim-lb.sqlite'}")
        factory = make_session_factory(engine)
        wait_for(lambda: first.poll() is None and _mid_run(factory), "the demo to be mid-run", timeout=300)
    finally:
        victims = [first.pid, *_processes_started_under(data_dir)]
        for pid in victims:
            with suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        first.wait()
    assert wait_for(lambda: _processes_started_under(data_dir) == [], "the killed processes to be gone")
    killed_at = time.monotonic()

    _demo_until_scored(command, tmp_path, env)
    print(f"demo restarted after a kill mid-run: all scored {time.monotonic() - killed_at:.1f} s after it")
    with factory() as session:
        every = session.scalars(select(Submission).order_by(Submission.id)).all()
        assert {s.status for s in every} == {Status.scored}  # the two-stage demo split's entries too
        submissions = [s for s in every if s.split.name == "demo"]
        assert [(s.method, s.status) for s in submissions] == [
            ("Constant Velocity", Status.scored),
            ("Human", Status.scored),
            ("Noisy human (demo)", Status.scored),
        ]
        keys = session.execute(
            select(
                TokenResultRow.submission_id,
                TokenResultRow.metric_version,
                TokenResultRow.seed,
                TokenResultRow.token,
            )
        ).all()
    # Every (submission, version, seed, token) once: the demo split's tokens, each version, one seed each.
    assert len(set(keys)) == len(keys)
    demo_ids = {s.id for s in submissions}
    per_submission = Counter(key.submission_id for key in keys if key.submission_id in demo_ids)
    assert per_submission == dict.fromkeys(
        (s.id for s in submissions), RESTART_SCENES * len(LOG_REPLAY_VERSIONS)
    )
    assert engine is not None
    engine.dispose()
    assert _processes_started_under(data_dir) == []
