"""Running a piece of work in a child process of its own, so that how the work ends is seen, not guessed.

A chunk whose process died is split one token per chunk (server.runs), and each such token is scored again
alone, here: in a child forked for it. If the child dies (a crash, or the kernel's out-of-memory killer, whose
first choice the child makes itself), the consumer that forked it sees how, and the token is written as
failed with that cause. If the consumer itself is killed from outside (an operator, a deployment, a lost
machine), its beat stops and the reaper sends the token again, as after any death: a kill from outside never
fails a token, however often it lands on the same one.

Fork rather than spawn: the child starts with the engine loaded, in the state the consumer is in, for the cost
of copying page tables. The forking thread is the consumer's main one; the others (beats) hold only database
connections, which the child never touches, and it leaves by `os._exit`, running no finaliser on what it
shares with its parent. Pooled object store connections are the child's own (server.object_store forgets
them at a fork). The child dies with its parent (PR_SET_PDEATHSIG): a consumer killed at its hard time limit
takes the work with it.
"""

from __future__ import annotations

import ctypes
import os
import pickle
import signal
import traceback
import warnings
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

_PR_SET_PDEATHSIG = 1
_OOM_SCORE_ADJ = Path("/proc/self/oom_score_adj")
_RETURNED, _RAISED = "returned", "raised"


@dataclass(frozen=True)
class ProcessDeath:
    """How an isolated child ended without handing back a result: the signal that killed it, or its exit
    status."""

    signal: int | None = None
    exit_status: int | None = None

    def __str__(self) -> str:
        if self.signal is None:
            return f"stopped with exit status {self.exit_status}"
        name = signal.Signals(self.signal).name
        if self.signal == signal.SIGKILL:  # what the out-of-memory killer sends
            return f"killed by {name} (most likely out of memory)"
        return f"killed by {name}"


class ChildTraceback(Exception):
    """The traceback of an exception raised in the child, as text: the cause of the one raised again here."""

    def __str__(self) -> str:
        return f"\n\nin the isolated process:\n{self.args[0]}"


def run_isolated(work: Callable[[], T]) -> T | ProcessDeath:
    """Return what `work()` returns, run in a forked child; raise what it raises (its traceback as the
    cause); return a ProcessDeath when the child dies. An exception here (the soft time limit's) kills the
    child."""
    parent = os.getpid()
    read_end, write_end = os.pipe()
    # Python 3.12 and later warn of any fork beside threads; the module's docstring says why this one is safe.
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "This process .* is multi-threaded", DeprecationWarning)
        child = os.fork()
    if child == 0:
        os.close(read_end)
        _run_child(work, write_end, parent)
    os.close(write_end)
    try:
        with os.fdopen(read_end, "rb") as results:
            payload = results.read()
        _, status = os.waitpid(child, 0)
    except BaseException:
        with suppress(ProcessLookupError):
            os.kill(child, signal.SIGKILL)
        os.waitpid(child, 0)
        raise
    if os.WIFSIGNALED(status):
        return ProcessDeath(signal=os.WTERMSIG(status))
    if os.WEXITSTATUS(status) != 0 or not payload:
        return ProcessDeath(exit_status=os.WEXITSTATUS(status))
    outcome, value, trace = pickle.loads(payload)
    if outcome == _RAISED:
        raise value from ChildTraceback(trace)
    return value


def _run_child(work: Callable[[], object], write_end: int, parent: int) -> None:
    """Run `work` in the child, write its outcome to `write_end`, and leave without returning."""
    status = 1
    try:
        _die_with(parent)
        with suppress(OSError):  # the out-of-memory killer's first choice: this child, not its parent
            _OOM_SCORE_ADJ.write_text("1000")
        try:
            payload = pickle.dumps((_RETURNED, work(), ""))
        except Exception as error:  # noqa: BLE001 - raised again in the parent
            payload = _pickled_error(error)
        with os.fdopen(write_end, "wb") as results:
            results.write(payload)
        status = 0
    finally:
        os._exit(status)


def _die_with(parent: int) -> None:
    """Have the kernel kill this child when its parent dies (Linux); leave at once if it already has."""
    with suppress(AttributeError, OSError):  # no prctl: not Linux
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:
        os._exit(1)


def _pickled_error(error: Exception) -> bytes:
    """Return `error` pickled with its traceback; an error that does not survive pickling as its text."""
    trace = traceback.format_exc()
    try:
        payload = pickle.dumps((_RAISED, error, trace))
        pickle.loads(payload)
    except Exception:  # noqa: BLE001 - whatever fails, the parent gets the error's text
        payload = pickle.dumps((_RAISED, RuntimeError(f"{type(error).__qualname__}: {error}"), trace))
    return payload
