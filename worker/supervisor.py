"""`navsim-lb worker`: one single-process Celery consumer per scoring process, and the reaper beside them,
kept alive and kept to their time limits by a supervisor that shares nothing with them but a pipe each.

Why not Celery's prefork pool: on the embedded broker (kombu's SQL transport, which has no event loop) the
pool's processes take their tasks from one shared queue behind one lock (billiard's SimpleQueue); a pool
process SIGKILLed while it held that lock wedged every other one for good, and the reaper, a task of the same
pool, with them. Here each consumer is a Celery worker of its own (`--pool solo`, one task at a time): it
takes a message from the broker itself (on SQLite in a `BEGIN IMMEDIATE` transaction, which a killed process
rolls back, its file lock gone with it), runs the task, acknowledges it. A killed consumer holds nothing
another process waits for; it is started again within a second, and the reaper sends its chunk again. The
same model runs on Redis, so every broker recovers the same way.

The supervisor:
- starts each child again when it exits, at once, or after a back-off when it keeps dying young;
- keeps the time limits the solo pool does not: a child reports each task it starts and ends
  (worker.supervised); past the task's soft limit it gets SIGUSR1 (a chunk fails its run cleanly), past
  its hard limit SIGKILL: a process that makes no progress while it holds work is replaced, and the reaper
  hands its work on (a stopped chunk beat);
- on SIGTERM or SIGINT, asks every child for a warm shutdown (each finishes its task) and exits after them.
It imports no Celery app: a wedged broker or database cannot stop it.

Scoring is batch work that shares its host with the API in the demo and in a one-host deployment: each
consumer starts at a lower priority (`--nice`, 10 by default: the kernel then gives it about a tenth of what a
request's process gets while both want a core) and with one BLAS thread (parallelism comes from the
consumers; OpenBLAS's threads would spin on the cores the API answers on). Both are set before the consumer's
interpreter starts: scorer loads numpy's OpenBLAS at its first import, which reads OPENBLAS_NUM_THREADS once.
The reaper keeps the supervisor's priority: its passes are short, and must not wait behind scoring.
"""

from __future__ import annotations

import logging
import os
import selectors
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from functools import partial
from types import FrameType

from worker.supervised import STATUS_FD

log = logging.getLogger("worker.supervisor")

TICK_S = 0.5
YOUNG_S = 10.0  # a child that dies younger than this may die of its start: it is started again after a wait
BACKOFF_MAX_S = 30.0
LOG_FORMAT = "[%(asctime)s: %(levelname)s/supervisor] %(message)s"
ONE_BLAS_THREAD = dict.fromkeys(("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"), "1")


@dataclass
class _Holding:
    """What a child said it holds, with its limits, as the supervisor's clock saw it start."""

    name: str
    since: float
    soft_limit: float | None
    hard_limit: float
    warned: bool = False  # SIGUSR1 sent


@dataclass
class Child:
    """A process the supervisor keeps running: a consumer or the reaper."""

    name: str
    command: list[str]
    niceness: int = 0  # added to the supervisor's, before the child's program starts
    environment: dict[str, str] = field(default_factory=dict)  # over the supervisor's
    process: subprocess.Popen[bytes] | None = None
    status: int | None = None  # the read end of the child's status pipe
    pending: bytes = b""
    started_at: float = 0.0
    start_after: float = 0.0
    young_deaths: int = 0
    holding: _Holding | None = None
    killed: bool = False  # by the supervisor, at a hard limit

    def start(self, selector: selectors.BaseSelector) -> None:
        read, write = os.pipe()
        env = {**os.environ, **self.environment, STATUS_FD: str(write)}
        # Same process group: a supervisor's own supervisor (the demo, a test) stops the lot with one signal.
        # Niceness is per thread on Linux: set before exec, every thread of the child has it. (The supervisor
        # runs no thread that could hold a lock in the forked child.)
        lower = partial(os.nice, self.niceness) if self.niceness else None
        self.process = subprocess.Popen(
            self.command,
            env=env,
            pass_fds=(write,),
            preexec_fn=lower,  # noqa: PLW1509
        )
        os.close(write)
        os.set_blocking(read, False)
        self.status, self.pending, self.holding, self.killed = read, b"", None, False
        self.started_at = time.monotonic()
        selector.register(read, selectors.EVENT_READ, self)
        log.info("started %s (pid %d)", self.name, self.process.pid)

    def read_status(self) -> None:
        assert self.status is not None
        try:
            data = os.read(self.status, 4096)
        except BlockingIOError:
            return
        *lines, self.pending = (self.pending + data).split(b"\n")
        for line in lines:
            self._apply(line.decode(errors="replace"))

    def _apply(self, line: str) -> None:
        kind, _, rest = line.partition(" ")
        if kind == "idle":
            self.holding = None
        elif kind == "busy":
            soft, hard, name = rest.split(" ", 2)
            limit = None if soft == "-" else float(soft)
            self.holding = _Holding(name, time.monotonic(), limit, float(hard))

    def keep_limits(self, now: float) -> None:
        """Send SIGUSR1 past the soft limit of what the child holds, SIGKILL past its hard limit."""
        held, process = self.holding, self.process
        if held is None or process is None or self.killed:
            return
        elapsed = now - held.since
        if elapsed >= held.hard_limit:
            log.error(
                "%s (pid %d) held %s for %.0f s, past its hard time limit: killed",
                self.name,
                process.pid,
                held.name,
                elapsed,
            )
            process.kill()
            self.killed = True
        elif held.soft_limit is not None and elapsed >= held.soft_limit and not held.warned:
            log.warning("%s (pid %d): %s past its soft time limit", self.name, process.pid, held.name)
            process.send_signal(signal.SIGUSR1)
            held.warned = True

    def reap(self, selector: selectors.BaseSelector, now: float, restart: bool) -> None:
        """Forget the child if it exited, and, with `restart`, schedule its next start."""
        process = self.process
        if process is None or process.poll() is None:
            return
        assert self.status is not None
        self.read_status()
        selector.unregister(self.status)
        os.close(self.status)
        self.process, self.status, self.holding = None, None, None
        if not restart:
            log.info("%s (pid %d) stopped with %s", self.name, process.pid, process.returncode)
            return
        young = now - self.started_at < YOUNG_S and not self.killed
        self.young_deaths = self.young_deaths + 1 if young else 0
        wait = min(2.0**self.young_deaths, BACKOFF_MAX_S) if young else 0.0
        self.start_after = now + wait
        log.warning(
            "%s (pid %d) exited with %s; starting it again in %.0f s",
            self.name,
            process.pid,
            process.returncode,
            wait,
        )


class Supervisor:
    """Keeps `children` running until SIGTERM or SIGINT, then stops them warmly."""

    def __init__(self, children: list[Child]) -> None:
        self.children = children
        self.selector = selectors.DefaultSelector()
        self.stopping = False

    def _stop(self, signum: int, frame: FrameType | None) -> None:
        if not self.stopping:
            log.info("stopping: a warm shutdown of every child (each finishes its task)")
        self.stopping = True
        for child in self.children:
            if child.process is not None and child.process.poll() is None:
                child.process.send_signal(signal.SIGTERM)

    def run(self) -> int:
        signal.signal(signal.SIGTERM, self._stop)
        signal.signal(signal.SIGINT, self._stop)
        while True:
            for key, _ in self.selector.select(TICK_S):
                key.data.read_status()
            now = time.monotonic()
            for child in self.children:
                child.reap(self.selector, now, restart=not self.stopping)
                child.keep_limits(now)
                if child.process is None and not self.stopping and now >= child.start_after:
                    child.start(self.selector)
            if self.stopping and all(child.process is None for child in self.children):
                log.info("stopped")
                return 0


def consumer_command(app: str, hostname: str, loglevel: str) -> list[str]:
    """Return the command line of one single-process Celery consumer of the configured queue."""
    return [
        sys.executable,
        "-m",
        "celery",
        f"--app={app}",
        "worker",
        "--pool=solo",
        "--concurrency=1",
        f"--hostname={hostname}",
        f"--loglevel={loglevel}",
        # Gossip, mingle and heartbeats synchronise revokes and events, which nothing here uses.
        "--without-gossip",
        "--without-mingle",
        "--without-heartbeat",
    ]


def reaper_command(app: str, loglevel: str) -> list[str]:
    """Return the command line of the reaper's process (worker.reaper)."""
    return [sys.executable, "-m", "worker.reaper", f"--app={app}", f"--loglevel={loglevel}"]


def _declare_queue() -> None:
    """Create the embedded broker's tables and the queue once, before consumers race to (Redis: a no-op)."""
    from server.queue import waiting_tasks
    from server.settings import get_settings

    try:
        waiting_tasks(get_settings(), declare=True)
    except Exception:  # the broker is away: each consumer waits for it and declares it itself
        log.warning("the broker's queue was not declared", exc_info=True)


def supervise(concurrency: int, reaper: bool, app: str, name: str, loglevel: str, niceness: int) -> int:
    """Run `concurrency` consumers (named NAME-1@host, ...), `niceness` below the supervisor, and, with
    `reaper`, the reaper; return the exit code."""
    logging.basicConfig(level=loglevel.upper(), format=LOG_FORMAT)
    _declare_queue()
    children = [
        Child(
            f"consumer {index}",
            consumer_command(app, f"{name}-{index}@%h", loglevel),
            niceness,
            ONE_BLAS_THREAD,
        )
        for index in range(1, concurrency + 1)
    ]
    if reaper:
        children.append(Child("reaper", reaper_command(app, loglevel)))
    return Supervisor(children).run()
