"""Servers of a test's own, which the test stops, kills, pauses and restarts: Redis and PostgreSQL, each on its
own port and data directory (never the machine's shared servers, which other tests use at the same time)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager, suppress
from pathlib import Path

import redis
from sqlalchemy import create_engine, text
from sqlalchemy.exc import OperationalError
from worker_testing import free_port, wait_for

from navsim_lb.processes import child_process

POSTGRES_USER = "postgres"  # PostgreSQL refuses to run as root


class OwnRedis:
    """A Redis server (no persistence, as the machine's) that the test can restart on the same port."""

    def __init__(self, directory: Path, host: str = "127.0.0.1") -> None:
        self.port, self.directory, self.host = free_port(), directory, host
        self.url = f"redis://{host}:{self.port}/0"
        self._process = ExitStack()
        self.process: subprocess.Popen[bytes] | None = None

    def client(self) -> redis.Redis:
        return redis.Redis(port=self.port)

    def start(self) -> None:
        command = [
            "redis-server",
            "--port",
            str(self.port),
            "--bind",
            *dict.fromkeys(["127.0.0.1", self.host]),
        ]
        command += ["--save", ""]
        if self.host != "127.0.0.1":  # bound to a veth pair's host side only: no password needed there either
            command += ["--protected-mode", "no"]
        command += ["--appendonly", "no", "--dir", str(self.directory)]
        log = self.directory / "redis.log"
        self.process = self._process.enter_context(child_process(command, dict(os.environ), log))
        wait_for(self._pings, f"redis on port {self.port}")

    def _pings(self) -> bool:
        try:
            return bool(self.client().ping())
        except redis.ConnectionError:
            return False

    def stop(self) -> None:
        self._process.close()

    def restart(self) -> None:
        self.stop()
        self.start()

    def kill(self) -> None:
        """SIGKILL the server (it keeps nothing: no persistence); `start` runs a new, empty one."""
        assert self.process is not None
        self.process.kill()
        self.stop()

    def pids(self) -> list[int]:
        assert self.process is not None
        return [self.process.pid]


@contextmanager
def own_redis(directory: Path, host: str = "127.0.0.1") -> Iterator[OwnRedis]:
    """Yield a running Redis server listening on loopback and on `host` (the host side of a veth pair, say)."""
    directory.mkdir()
    server = OwnRedis(directory, host)
    server.start()
    try:
        yield server
    finally:
        server.stop()


def _postgres_bin(program: str) -> str:
    found = shutil.which(program) or next(Path("/usr/lib/postgresql").glob(f"*/bin/{program}"), None)
    assert found is not None, f"{program} is not installed (Debian package postgresql)"
    return str(found)


class OwnPostgres:
    """A PostgreSQL cluster in a temporary directory, run by the postgres user, that the test stops and starts."""

    def __init__(self, directory: Path, host: str = "127.0.0.1") -> None:
        self.directory, self.port, self.host = directory, free_port(), host
        self.url = f"postgresql://{POSTGRES_USER}@{host}:{self.port}/postgres"

    def _as_postgres(self, *command: str) -> None:
        subprocess.run(["runuser", "-u", POSTGRES_USER, "--", *command], check=True, capture_output=True)

    def initialise(self) -> None:
        self._as_postgres(
            _postgres_bin("initdb"), "-D", str(self.directory / "data"), "-A", "trust", "-U", "postgres"
        )
        if self.host != "127.0.0.1":  # clients on the host's side of veth pairs (tests/netns.py)
            with (self.directory / "data" / "pg_hba.conf").open("a") as rules:
                rules.write(f"host all all {self.host.rsplit('.', 2)[0]}.0.0/16 trust\n")

    def start(self) -> None:
        listen = ",".join(dict.fromkeys(["127.0.0.1", self.host]))
        options = f"-p {self.port} -k {self.directory} -c listen_addresses={listen}"
        log = str(self.directory / "postgres.log")
        self._as_postgres(
            _postgres_bin("pg_ctl"),
            "-D",
            str(self.directory / "data"),
            "-o",
            options,
            "-l",
            log,
            "-w",
            "start",
        )
        wait_for(self._answers, f"postgresql on port {self.port}")

    def _answers(self) -> bool:
        engine = create_engine(self.url.replace("postgresql://", "postgresql+psycopg://"))
        try:
            with engine.connect() as connection:
                return connection.execute(text("SELECT 1")).scalar() == 1
        except OperationalError:
            return False
        finally:
            engine.dispose()

    def stop(self) -> None:
        self._as_postgres(
            _postgres_bin("pg_ctl"), "-D", str(self.directory / "data"), "-m", "fast", "-w", "stop"
        )

    def pids(self) -> list[int]:
        """Return the cluster's processes: the postmaster first, then its children (Linux /proc)."""
        postmaster = int((self.directory / "data" / "postmaster.pid").read_text().split()[0])
        children = []
        for task in Path(f"/proc/{postmaster}/task").iterdir():
            children += [int(pid) for pid in (task / "children").read_text().split()]
        return [postmaster, *children]

    def kill(self) -> None:
        """SIGKILL every process of the cluster at once, as the kernel's out-of-memory killer of a container
        would, and wait until they are gone; `start` then recovers it from its write-ahead log."""
        pids = self.pids()
        for pid in pids:
            with suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        while any(_alive(pid) for pid in pids):
            time.sleep(0.05)
        # Its lock files name the dead postmaster, which may linger as a zombie that nobody waits for: a new
        # postmaster would take it for a running server (a restarted container starts without them).
        (self.directory / "data" / "postmaster.pid").unlink(missing_ok=True)
        (self.directory / f".s.PGSQL.{self.port}.lock").unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie, killed and not yet waited for by its parent, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


@contextmanager
def paused(pids: list[int]) -> Iterator[None]:
    """SIGSTOP the processes for the block (a server that hangs: its clients' connections stay open and
    unanswered), SIGCONT them afterwards, whatever happens."""
    for pid in pids:
        os.kill(pid, signal.SIGSTOP)
    try:
        yield
    finally:
        for pid in pids:
            with suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)


@contextmanager
def own_postgres(host: str = "127.0.0.1") -> Iterator[OwnPostgres]:
    """Yield a running cluster of the test's own, listening on loopback and on `host`; removed afterwards (its
    directory must be the postgres user's)."""
    directory = Path(tempfile.mkdtemp(prefix="navsim-lb-postgres-"))
    try:
        directory.chmod(0o755)
        shutil.chown(directory, POSTGRES_USER, POSTGRES_USER)
        server = OwnPostgres(directory, host)
        server.initialise()
        server.start()
        try:
            yield server
        finally:
            with suppress(subprocess.CalledProcessError):  # already stopped
                server.stop()
    finally:
        shutil.rmtree(directory, ignore_errors=True)
