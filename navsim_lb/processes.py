"""Child processes of the demo, the tests and the benchmarks: each in its own session, always stopped."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

STOP_TIMEOUT_S = 20.0


def api_command(host: str, port: int) -> list[str]:
    """Return the command line of one API process (uvicorn) configured from the environment."""
    return [
        sys.executable,
        "-m",
        "uvicorn",
        "server.main:app_from_environment",
        "--factory",
        "--host",
        host,
        "--port",
        str(port),
    ]


@contextmanager
def child_process(command: list[str], env: dict[str, str], log: Path) -> Iterator[subprocess.Popen[bytes]]:
    """Run `command` for the block with its output in `log`; stop it, and whatever it forked, afterwards.

    Its own session keeps a terminal's Ctrl-C away from it: the parent decides when and how it stops.
    """
    with log.open("ab") as handle:
        process = subprocess.Popen(
            command, env=env, stdout=handle, stderr=subprocess.STDOUT, start_new_session=True
        )
    try:
        yield process
    finally:
        if process.poll() is None:
            process.terminate()  # warm shutdown: Celery finishes its running tasks, uvicorn its requests
        with suppress(subprocess.TimeoutExpired):
            process.wait(timeout=STOP_TIMEOUT_S)
        with suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)  # pool processes or a beat that outlived their parent
        process.wait()
