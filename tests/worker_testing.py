"""Fixtures and helpers of the worker tests: a small synthetic split with its metric cache, and a running
service (a real Celery worker process and a uvicorn API process) on a database and broker of choice."""

from __future__ import annotations

import os
import socket
import subprocess
import time
import zlib
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from navsim_lb.processes import api_command, child_process
from scorer.baselines import baseline_submission
from scorer.evaluate import build_split_cache, score_tokens, summarize
from scorer.submission import Submission as Predictions
from scorer.submission import SubmissionMetadata, dump_submission_json
from scorer.synth import synthesize_split
from scorer.versions import LOG_REPLAY_VERSIONS, get_version
from server.db import make_engine, make_session_factory, transaction
from server.migrate import upgrade
from server.models import (
    ACTIVE_STATUSES,
    Approval,
    Phase,
    Scope,
    Status,
    Submission,
    Summary,
    Team,
    TokenResultRow,
    utc_now,
)
from server.services.splits import create_phase, register_split, split_tokens
from server.services.submissions import create_submission
from server.services.teams import create_team
from server.services.tokens import create_token
from server.services.validation import validate_upload
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
    failures = build_split_cache(directory, cache_dir, list(LOG_REPLAY_VERSIONS), workers=2)
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
    columns = get_version(version).result_columns
    per_seed = [
        summarize(score_tokens(split.directory, split.cache_dir, poses, version, seed=seed), columns)
        for seed, poses in enumerate(submission.seeds)
    ]
    return {column: float(np.mean([summary[column] for summary in per_seed])) for column in columns}


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
    api: subprocess.Popen[bytes]

    def client(self) -> httpx.Client:
        return httpx.Client(
            base_url=self.url, headers={"Authorization": f"Bearer {self.team_token}"}, timeout=30
        )

    def worker_log(self) -> str:
        return (self.logs / "worker.log").read_text(errors="replace")

    def submission(self, submission_id: int) -> Submission:
        with self.factory() as session:
            submission = session.get(Submission, submission_id)
            assert submission is not None
            return submission

    def final(self, submission_id: int, timeout: float = SERVICE_TIMEOUT_S) -> Submission:
        """Wait until a submission is scored, failed or cancelled; return it."""
        return wait_for(  # type: ignore[return-value]
            lambda: (s := self.submission(submission_id)).status not in ACTIVE_STATUSES and s,
            f"submission {submission_id} to finish",
            timeout,
        )

    def stored(self, entry: Predictions, phase: str = "test", lost_claims: int = 0) -> int:
        """Create a queued submission through the services, without sending it to the workers; return its id.

        With `lost_claims`, it is created running instead, as if a worker had claimed it that many times, the
        last 5 s ago, and died before planning: in the same transaction, so that no reaper pass finds it queued
        (and sends it) in between.
        """
        data = dump_submission_json(entry)
        with transaction(self.factory) as session:
            phase_row = session.scalar(select(Phase).where(Phase.name == phase))
            team = session.scalar(select(Team).where(Team.name == "alpha"))
            assert phase_row is not None and team is not None
            upload = validate_upload(data, "entry.json", split_tokens(phase_row.split))
            submission, _ = create_submission(
                session, team, phase_row, upload, self.settings.submission_store
            )
            if lost_claims:
                submission.status, submission.attempts, submission.worker = (
                    Status.running,
                    lost_claims,
                    "lost",
                )
                submission.claimed_at = utc_now() - timedelta(seconds=5)
            return submission.id

    def upload(self, entry: Predictions, name: str = "entry.json") -> int:
        """Upload a submission through the API as the team; return its id."""
        with self.client() as client:
            response = client.post(
                "/api/v1/submissions",
                files={"file": (name, dump_submission_json(entry))},
                data={"phase": "test"},
            )
        assert response.status_code == 202, response.text
        return int(response.json()["id"])

    def rows(self, submission_id: int) -> int:
        """Return how many per-token rows of the submission are stored."""
        with self.factory() as session:
            query = select(func.count()).where(TokenResultRow.submission_id == submission_id)
            return session.scalar(query) or 0

    def leaderboard_row(self, version: str, submission_id: int) -> dict[str, Any]:
        """Return the submission's one row on the public leaderboard of phase "test"."""
        with self.client() as client:
            response = client.get("/api/v1/leaderboard", params={"version": version, "phase": "test"})
        assert response.status_code == 200, response.text
        rows = [row for row in response.json()["rows"] if row["submission_id"] == submission_id]
        assert len(rows) == 1, response.json()["rows"]
        return rows[0]

    def result(self, submission_id: int, version: str) -> dict[str, Any]:
        """Return a submission's results on all tokens under `version`, as the team sees them."""
        with self.client() as client:
            response = client.get(f"/api/v1/submissions/{submission_id}")
        assert response.status_code == 200, response.text
        return response.json()["results"][version]["all"]


def assert_scored_once(service: Service, split: SplitFixture, submission_id: int, entry: Predictions) -> None:
    """The submission is scored with every row once, one leaderboard entry per version, the engine's numbers."""
    submission = service.submission(submission_id)
    assert submission.status == Status.scored, (submission.status, submission.error, submission.error_detail)
    assert service.rows(submission_id) == len(entry.seeds[0]) * len(entry.seeds) * len(LOG_REPLAY_VERSIONS)
    with service.factory() as session:
        query = select(Summary.metric_version, func.count()).where(Summary.submission_id == submission_id)
        entries = dict(session.execute(query.group_by(Summary.metric_version)).all())
    assert entries == dict.fromkeys(LOG_REPLAY_VERSIONS, 1)  # the split has one subset, "all"
    for version in LOG_REPLAY_VERSIONS:
        expected = direct_means(split, entry, version)["score"]
        assert service.result(submission_id, version)["score"] == pytest.approx(expected, rel=1e-12)


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


def api_answers(url: str) -> bool:
    """Whether the API at `url` answers its health check with 200."""
    try:
        return httpx.get(f"{url}/api/v1/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def fault_worker_command(concurrency: int, reaper: bool, name: str) -> list[str]:
    """Return the command of a worker named `name` running tests/fault_worker.py's app (faults from the env)."""
    return worker_command(concurrency, reaper, app="fault_worker", name=name)


def supervised_processes(supervisor: int) -> tuple[list[int], list[int]]:
    """Return the pids of a worker's consumers and of its reaper: its supervisor's children (Linux /proc)."""
    consumers, reapers = [], []
    for task in Path(f"/proc/{supervisor}/task").iterdir():
        for pid in (task / "children").read_text().split():
            try:
                command = Path(f"/proc/{pid}/cmdline").read_bytes()
            except OSError:  # exited meanwhile
                continue
            (reapers if b"worker.reaper" in command else consumers).append(int(pid))
    return consumers, reapers


def alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie, killed and not yet waited for, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@contextmanager
def running_service(
    root: Path,
    split: SplitFixture,
    overrides: dict[str, str] | None = None,
    concurrency: int = 2,
    faults: bool = False,
    split_location: str | None = None,
    worker_prefix: Sequence[str] = (),
) -> Iterator[Service]:
    """Start worker (with the reaper) and API on a fresh database under `root`, configured by the environment.

    With `faults`, the worker runs tests/fault_worker.py's app, which injects the faults `overrides` name.
    `split_location` registers the split from there (an object store's prefix) instead of its directory.
    The worker's command is run after `worker_prefix` (`ip netns exec NAME`: tests/netns.py).
    """
    variables = _variables(root, split, overrides or {})
    if faults:
        variables["PYTHONPATH"] = os.pathsep.join(
            filter(None, [str(Path(__file__).parent), os.getenv("PYTHONPATH")])
        )
    env = {**os.environ, **variables}
    with pytest.MonkeyPatch.context() as patch:  # the test reads the settings the children will read
        for name, value in variables.items():
            patch.setenv(name, value)
        settings = Settings()
    upgrade(settings.database_url)
    engine = make_engine(settings.database_url)
    factory = make_session_factory(engine)
    with transaction(factory) as session:
        registered = register_split(session, "synthetic", split_location or split.directory)
        create_phase(session, "test", registered)
        team = create_team(session, "alpha", ["a member"], "a lab", Approval.approved)
        _, team_token = create_token(session, Scope.team, team, "test")
    logs = root / "logs"
    logs.mkdir(exist_ok=True)
    port = free_port()
    try:
        with ExitStack() as stack:
            worker = stack.enter_context(
                child_process(
                    [
                        *worker_prefix,
                        *(
                            fault_worker_command(concurrency, True, "first")
                            if faults
                            else worker_command(concurrency, reaper=True)
                        ),
                    ],
                    env,
                    logs / "worker.log",
                )
            )
            # Only the worker creates the embedded broker's tables, before anything is sent.
            wait_for(
                lambda: "ready." in (logs / "worker.log").read_text(errors="replace"), "the worker to start"
            )
            api = stack.enter_context(child_process(api_command("127.0.0.1", port), env, logs / "api.log"))
            url = f"http://127.0.0.1:{port}"
            wait_for(lambda: api_answers(url), "the API to answer")
            yield Service(settings, env, factory, url, team_token, logs, worker, api)
    finally:
        engine.dispose()


def write_submission(path: Path, submission: Predictions) -> Path:
    """Write a submission as navsim-lb JSON and return its path."""
    path.write_bytes(dump_submission_json(submission))
    return path
