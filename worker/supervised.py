"""The side of a process that worker.supervisor runs (a consumer, the reaper): it says what it holds, takes the
soft time limit, and stops with its supervisor.

It writes one line to the pipe the supervisor gave it (STATUS_FD) when it starts a piece of work
(`busy <soft limit or -> <hard limit> <name>`) and when it ends it (`idle`); the supervisor keeps the time
limits from those lines. The writes never block: a supervisor that stopped reading must not stop its children.
The soft limit arrives as SIGUSR1, as in Celery's prefork pool, and raises SoftTimeLimitExceeded only in work
that has one and ran past it: a signal that arrives late, after that work ended, must not hit the next.
A supervisor that dies (SIGKILL, out of memory) leaves its children behind: each then asks itself for a warm
shutdown (SIGTERM), finishing what it holds, and the supervisor started in its place starts fresh ones.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from contextlib import suppress
from dataclasses import dataclass
from types import FrameType

from celery.exceptions import SoftTimeLimitExceeded

STATUS_FD = "NAVSIM_LB_STATUS_FD"
PARENT_POLL_S = 1.0


@dataclass(frozen=True)
class _Held:
    name: str
    since: float  # time.monotonic()
    soft_limit: float | None


_held: _Held | None = None
_watching = threading.Event()


def _status_fd() -> int | None:
    value = os.environ.get(STATUS_FD)
    return int(value) if value else None


def _report(line: str) -> None:
    fd = _status_fd()
    if fd is None:
        return
    # Shorter than PIPE_BUF: written whole or not at all. A supervisor gone, or a full pipe: the next line tells.
    with suppress(OSError):
        os.write(fd, f"{line}\n".encode())


def report_busy(name: str, soft_limit: float | None, hard_limit: float) -> None:
    """Say that this process started `name`, to be stopped past its limits (in seconds)."""
    global _held
    _held = _Held(name, time.monotonic(), soft_limit)
    soft = "-" if soft_limit is None else f"{soft_limit:.3f}"
    _report(f"busy {soft} {hard_limit:.3f} {name}")


def report_idle() -> None:
    """Say that this process holds no work."""
    global _held
    _held = None
    _report("idle")


def _soft_limit_reached(signum: int, frame: FrameType | None) -> None:
    held = _held
    if held is not None and held.soft_limit is not None and time.monotonic() - held.since >= held.soft_limit:
        raise SoftTimeLimitExceeded(f"{held.name} ran past its soft time limit of {held.soft_limit:.0f} s")


def _stop_with(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(PARENT_POLL_S)
    os.kill(os.getpid(), signal.SIGTERM)


def become_supervised() -> None:
    """Under a supervisor (STATUS_FD set): take its soft limits, and stop when it dies. Call it from the main
    thread, after Celery installed its own signal handlers; a second call does nothing."""
    fd = _status_fd()
    if fd is None or _watching.is_set():
        return
    _watching.set()
    os.set_blocking(fd, False)
    signal.signal(signal.SIGUSR1, _soft_limit_reached)
    threading.Thread(target=_stop_with, args=(os.getppid(),), name="supervisor-watch", daemon=True).start()
