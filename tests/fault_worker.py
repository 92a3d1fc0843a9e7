"""The workers' Celery app with faults injected from the environment, for tests/test_worker_faults.py only.

FAULT_CHUNK_SECONDS: every chunk sleeps this long before it scores, so that a test can kill it mid-chunk.
FAULT_POISON_TOKEN: a chunk holding this token kills its own process (SIGKILL), as a segfault or the
kernel's out-of-memory killer would, every time.
FAULT_HANG_TOKEN: a chunk holding this token hangs where the soft time limit cannot interrupt it (as C code
that never returns to Python), so only the hard time limit stops it; with FAULT_HANG_MARKER, only the first
such chunk, which creates that file.
FAULT_PLAN_SECONDS, FAULT_REAP_SECONDS: planning a submission's chunks, and each pass of the reaper, take this
much longer (a slow database), so that a test can hold them past the chunks' soft time limit.
FAULT_WRITE_MARKER: the first chunk to write its rows creates this file, holding its pid, and waits
FAULT_WRITE_SECONDS inside the write's transaction, so that a test can kill the process while it writes.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Sequence
from typing import Any

import scorer.evaluate
import server.runs
import server.runs._plan
import worker.tasks
from worker.app import app

__all__ = ["app"]
_score_seeds = scorer.evaluate.score_seeds
_plan_chunks = server.runs._plan.plan_chunks
_prune_embedded_broker = worker.tasks.prune_embedded_broker
_write_chunk = server.runs.write_chunk


def _faulty_score_seeds(
    split_dir: Any,
    cache_dir: Any,
    seeds: Any,
    versions: Sequence[str],
    tokens: Sequence[str],
    context: Sequence[str] = (),
    scenes: Any = None,
) -> Any:
    if os.environ.get("FAULT_POISON_TOKEN") in tokens:
        os.kill(os.getpid(), signal.SIGKILL)
    if os.environ.get("FAULT_HANG_TOKEN") in tokens and _first_to_claim(os.environ.get("FAULT_HANG_MARKER")):
        signal.signal(signal.SIGUSR1, signal.SIG_IGN)  # Celery's soft time limit arrives as SIGUSR1
        while True:
            time.sleep(1)
    time.sleep(float(os.environ.get("FAULT_CHUNK_SECONDS", "0")))
    return _score_seeds(split_dir, cache_dir, seeds, versions, tokens, context=context, scenes=scenes)


def _slow_plan_chunks(*args: Any) -> Any:
    time.sleep(float(os.environ.get("FAULT_PLAN_SECONDS", "0")))
    return _plan_chunks(*args)


def _slow_prune_embedded_broker(settings: Any) -> int:
    time.sleep(float(os.environ.get("FAULT_REAP_SECONDS", "0")))
    return _prune_embedded_broker(settings)


def _first_to_claim(marker: str | None) -> bool:
    """Whether this process is the first to create `marker` (writing its pid there); True without a marker."""
    if not marker:
        return True
    try:
        descriptor = os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL)
    except FileExistsError:
        return False
    os.write(descriptor, str(os.getpid()).encode())
    os.close(descriptor)
    return True


def _slow_first_write_chunk(*args: Any, **kwargs: Any) -> Any:
    written = _write_chunk(*args, **kwargs)
    marker = os.environ.get("FAULT_WRITE_MARKER")
    if marker and _first_to_claim(marker):
        time.sleep(float(os.environ.get("FAULT_WRITE_SECONDS", "0")))
    return written


scorer.evaluate.score_seeds = _faulty_score_seeds  # server.runs imports it where it scores
server.runs._plan.plan_chunks = _slow_plan_chunks
worker.tasks.prune_embedded_broker = _slow_prune_embedded_broker
server.runs.write_chunk = _slow_first_write_chunk  # worker.tasks calls it through the package
