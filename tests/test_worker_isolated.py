"""Work run in a child process of its own (worker.isolated): its result or its exception comes back as if run
here, its death is told apart by signal, it dies with its parent and with an exception here, it is the
out-of-memory killer's first choice, and it never uses its parent's pooled object store connections."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from worker_testing import wait_for

from server.models import FailureKind
from server.object_store import StoreUnavailable, _client_of
from server.runs import Rejected
from worker.isolated import ChildTraceback, ProcessDeath, run_isolated


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_a_result_comes_back_as_returned() -> None:
    result = run_isolated(lambda: {"pid": os.getpid(), "values": [1.5, None]})
    assert isinstance(result, dict) and result["values"] == [1.5, None] and result["pid"] != os.getpid()


def _divide() -> float:
    return 1 / 0


def test_an_exception_is_raised_again_with_the_childs_traceback_as_its_cause() -> None:
    with pytest.raises(ZeroDivisionError) as raised:
        run_isolated(_divide)
    cause = raised.value.__cause__
    assert isinstance(cause, ChildTraceback) and "in _divide" in str(cause) and "return 1 / 0" in str(cause)


def _reject() -> None:
    raise Rejected(FailureKind.submission, "the file is not a submission", "row 3: no token")


def _store_away() -> None:
    raise StoreUnavailable("object store s3://bucket cannot be reached")


class _Unpicklable(Exception):
    def __init__(self, first: str, second: str) -> None:
        super().__init__(f"{first} and {second}")


def _unpicklable() -> None:
    raise _Unpicklable("one", "two")


def test_the_errors_a_run_handles_keep_their_type_and_fields() -> None:
    """Rejected fails the run with its own message, StoreUnavailable makes the chunk wait: both must arrive as
    themselves; an error that cannot travel arrives as its text."""
    with pytest.raises(Rejected) as rejected:
        run_isolated(_reject)
    assert (rejected.value.kind, rejected.value.message, rejected.value.detail) == (
        FailureKind.submission,
        "the file is not a submission",
        "row 3: no token",
    )
    with pytest.raises(StoreUnavailable, match="cannot be reached"):
        run_isolated(_store_away)
    with pytest.raises(RuntimeError, match="_Unpicklable: one and two"):
        run_isolated(_unpicklable)


@pytest.mark.parametrize(
    ("sent", "told"),
    [
        (signal.SIGSEGV, "killed by SIGSEGV"),
        (signal.SIGABRT, "killed by SIGABRT"),
        (signal.SIGKILL, "killed by SIGKILL (most likely out of memory)"),
    ],
)
def test_a_death_is_told_by_its_signal(sent: int, told: str) -> None:
    death = run_isolated(lambda: os.kill(os.getpid(), sent))
    assert death == ProcessDeath(signal=sent) and str(death) == told


def test_an_exit_without_a_result_is_a_death() -> None:
    death = run_isolated(lambda: os._exit(3))
    assert death == ProcessDeath(exit_status=3) and str(death) == "stopped with exit status 3"


def test_the_child_is_the_out_of_memory_killers_first_choice() -> None:
    assert run_isolated(lambda: Path("/proc/self/oom_score_adj").read_text().strip()) == "1000"
    assert Path("/proc/self/oom_score_adj").read_text().strip() != "1000"


def test_the_child_dies_with_its_parent(tmp_path: Path) -> None:
    """A consumer killed (at its hard time limit, from outside) takes its isolated work with it."""
    pid_file = tmp_path / "child.pid"
    script = textwrap.dedent(
        f"""
        import os, time
        from pathlib import Path
        from worker.isolated import run_isolated
        def work():
            Path({str(pid_file)!r}).write_text(str(os.getpid()))
            time.sleep(60)
        run_isolated(work)
        """
    )
    parent = subprocess.Popen([sys.executable, "-c", script], env={**os.environ, "PYTHONPATH": os.getcwd()})
    try:
        wait_for(
            lambda: pid_file.exists() and pid_file.read_text(), "the isolated child to start", timeout=30
        )
        child = int(pid_file.read_text())
        assert _alive(child)
        parent.kill()
        parent.wait()
        wait_for(lambda: not _alive(child), "the isolated child to die with its parent", timeout=10)
    finally:
        parent.kill()
        parent.wait()


class _SoftLimit(Exception):
    pass


def _soft_limit(signum: int, frame: object) -> None:
    raise _SoftLimit


def test_an_exception_here_while_the_child_works_kills_it(tmp_path: Path) -> None:
    """The soft time limit arrives in the parent as a signal whose handler raises: the child goes too."""
    pid_file = tmp_path / "child.pid"

    def work() -> None:
        pid_file.write_text(str(os.getpid()))
        time.sleep(60)

    previous = signal.signal(signal.SIGALRM, _soft_limit)
    try:
        signal.setitimer(signal.ITIMER_REAL, 1.0)
        with pytest.raises(_SoftLimit):
            run_isolated(work)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert not _alive(int(pid_file.read_text()))  # killed and reaped before the exception went on


def test_the_child_makes_its_own_object_store_client() -> None:
    """Pooled connections shared with the parent would cross replies: the child starts without the parent's."""
    _client_of("http://127.0.0.1:1")
    assert _client_of.cache_info().currsize >= 1
    assert run_isolated(lambda: _client_of.cache_info().currsize) == 0
    assert _client_of.cache_info().currsize >= 1
