"""What the supervisor gives each consumer before its interpreter starts: a lower priority and one BLAS thread
(worker.supervisor); the reaper keeps the supervisor's priority."""

from __future__ import annotations

import os
import selectors
import sys
from pathlib import Path

from worker.supervisor import ONE_BLAS_THREAD, Child

PROBE = """
import os, sys
threads = [os.environ.get(name, "unset") for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")]
open(sys.argv[1], "w").write(" ".join([str(os.nice(0)), *threads]))
"""


def _started(tmp_path: Path, child: Child) -> str:
    """Start `child` (a probe writing its niceness and BLAS variables to a file); return what it wrote."""
    selector = selectors.DefaultSelector()
    child.start(selector)
    assert child.process is not None
    assert child.process.wait(timeout=60) == 0
    child.reap(selector, 0.0, restart=False)
    return (tmp_path / child.name).read_text()


def test_a_consumer_starts_niced_with_one_blas_thread(tmp_path: Path) -> None:
    probe = [sys.executable, "-c", PROBE, str(tmp_path / "consumer")]
    niceness = min(os.nice(0) + 7, 19)
    assert _started(tmp_path, Child("consumer", probe, 7, ONE_BLAS_THREAD)) == f"{niceness} 1 1 1"


def test_a_child_without_niceness_keeps_the_supervisors_priority(tmp_path: Path) -> None:
    probe = [sys.executable, "-c", PROBE, str(tmp_path / "reaper")]
    blas = " ".join(os.environ.get(name, "unset") for name in ONE_BLAS_THREAD)
    assert _started(tmp_path, Child("reaper", probe)) == f"{os.nice(0)} {blas}"
