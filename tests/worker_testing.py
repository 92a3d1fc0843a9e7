"""Fixtures and helpers of the worker tests: a small synthetic split with its metric cache, and a running
service (a real Celery worker process and a uvicorn API process) on a database and broker of choice."""

from __future__ import annotations

import os
import socket
import subprocess
import time
import zlib
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from sqlalchemy.orm import Session, sessionmaker

from navsim_lb.processes import api_command, child_process
from scorer.baselines import baseline_submission
from scorer.evaluate import build_split_cache, score_tokens, summarize
from scorer.submission import Submission as Predictions
from scorer.submission import SubmissionMetadata, dump_submission_json
from scorer.synth import synthesize_split
from scorer.versions import METRIC_COLUMNS, VERSIONS
from server.db import make_engine, make_session_factory, transaction
from server.migrate import upgrade
from server.models import Approval, Scope
from server.services.splits import create_phase, register_split
from server.services.teams import create_team
from server.services.tokens import create_token
from server.settings import Settings
from worker.cli import worker_command

SPLIT_SCENES = 12
SPLIT_SEED = 5
SERVICE_TIMEOUT_S = 120.0  # a deadline against hanging, not a speed requirement


@dataclass(frozen=True)
class SplitFixture:
    directory: Path
    cache_dir: Path


@pytest.fixture(scope="session")
def synthetic_split(tmp_path_factory: pytest.TempPathFactory) -> SplitFixture:
    """A 12-scene synthetic split with the metric caches of every version already built."""
    root = tmp_path_factory.mktemp("worker-split")
    directory, cache_dir = root / "split", root / "cache"
    synthesize_split(directory, SPLIT_SCENES, SPLIT_SEED)
    failures = build_split_cache(directory, cache_dir, list(VERSIONS), workers=2)
    assert not failures, failures
    return SplitFixture(directory, cache_dir)


def wait_for(condition: Callable[[], object], what: str, timeout: float = SERVICE_TIMEOUT_S) -> object:
    """Return the first truthy value of `condition()`, polled; fail naming `what` after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.2)
    pytest.fail(f"gave up waiting for {what} after {timeout:.0f} s")


def free_port() -> int:
    """Return a TCP port on the loopback interface nobody listens on right now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def predictions(split_dir: Path, seeds: int, noise: float, method: str) -> Predictions:
    """Return the human trajectories with seeded noise, one noisy copy per seed (a multi-seed submission)."""
    human = baseline_submission(split_dir, "human", method).seeds[0]
    rng = np.random.default_rng(zlib.crc32(method.encode()))
    per_seed = tuple(
        {token: poses + rng.normal(0.0, noise, poses.shape) for token, poses in human.items()}
        for _ in range(seeds)
    )
    return Predictions(SubmissionMetadata(method=method), per_seed)


def direct_means(split: SplitFixture, submission: Predictions, version: str) -> dict[str, float]:
    """Return each metric column averaged over seeds and tokens, scored by scorer.evaluate directly."""
    per_seed = [
        summarize(score_tokens(split.directory, split.cache_dir, poses, version, seed=seed))
        for seed, poses in enumerate(submission.seeds)
    ]
    return {column: float(np.mean([summary[column] for summary in per_seed])) for column in METRIC_COLUMNS}


@dataclass
class Service:
    """A migrated database with the split, a phase and a team, and running worker and API processes."""

    settings: Settings
    env: dict[str, str]
    factory: sessionmaker[Session]
    url: str
    team_token: str
    logs: Path
    worker: subprocess.Popen[bytes]

    def client(self) -> httpx.Client:
        return httpx.Client(
            base_url=self.url, headers={"Authorization": f"Bearer {self.team_token}"}, timeout=30
        )

    def worker_log(self) -> str:
        return (self.logs / "worker.log").read_text(errors="replace")


def _variables(root: Path, split: SplitFixture, overrides: dict[str, str]) -> dict[str, str]:
    """Return the environment variables configuring one service under `root`, on its own broker queue."""
    return {
        "DATA_DIR": str(root),
        "CACHE_DIR": str(split.cache_dir),
        "QUEUE_NAME": f"navsim-lb-test-{root.name}-{os.getpid()}",
        "BOOTSTRAP_SAMPLES": "200",
        "LEADERBOARD_CACHE_SECONDS": "0",
        "SPLITS": "{}",
        **overrides,
    }


def _answers(url: str) -> bool:
    try:
        return httpx.get(f"{url}/api/v1/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


@contextmanager
def running_service(
    root: Path, split: SplitFixture, overrides: dict[str, str] | None = None, concurrency: int = 2
) -> Iterator[Service]:
    """Start worker (with beat) and API on a fresh database under `root`, configured by the environment."""
    variables = _variables(root, split, overrides or {})
    env = {**os.environ, **variables}
    with pytest.MonkeyPatch.context() as patch:  # the test reads the settings the children will read
        for name, value in variables.items():
            patch.setenv(name, value)
        settings = Settings()
    upgrade(settings.database_url)
    engine = make_engine(settings.database_url)
    factory = make_session_factory(engine)
    with transaction(factory) as session:
        registered = register_split(session, "synthetic", split.directory)
        create_phase(session, "test", registered)
        team = create_team(session, "alpha", ["a member"], "a lab", Approval.approved)
        _, team_token = create_token(session, Scope.team, team, "test")
    logs = root / "logs"
    logs.mkdir(exist_ok=True)
    port = free_port()
    try:
        with ExitStack() as stack:
            worker = stack.enter_context(
                child_process(worker_command(concurrency, beat=True), env, logs / "worker.log")
            )
            # Only the worker creates the embedded broker's tables, before anything is sent.
            wait_for(
                lambda: "ready." in (logs / "worker.log").read_text(errors="replace"), "the worker to start"
            )
            stack.enter_context(child_process(api_command("127.0.0.1", port), env, logs / "api.log"))
            url = f"http://127.0.0.1:{port}"
            wait_for(lambda: _answers(url), "the API to answer")
            yield Service(settings, env, factory, url, team_token, logs, worker)
    finally:
        engine.dispose()


def write_submission(path: Path, submission: Predictions) -> Path:
    """Write a submission as navsim-lb JSON and return its path."""
    path.write_bytes(dump_submission_json(submission))
    return path
