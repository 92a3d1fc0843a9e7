"""`navsim-lb demo --exit-when-scored` end to end on a fresh directory: the embedded defaults, a worker and
the API as child processes, baselines and the demo entry scored, tokens written, every child stopped."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from sqlalchemy import select
from worker_testing import free_port

from server.db import make_engine, make_session_factory
from server.models import Status, Submission

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


def test_demo_runs_end_to_end_and_stops_what_it_started(tmp_path: Path) -> None:
    env = {key: value for key, value in os.environ.items() if key not in SETTINGS_VARIABLES}
    done = subprocess.run(
        [NAVSIM_LB, "demo", "--scenes", "12", "--port", str(free_port()), "--exit-when-scored"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    data_dir = tmp_path / ".navsim-lb"
    assert "leaderboard: http://" in done.stderr
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
