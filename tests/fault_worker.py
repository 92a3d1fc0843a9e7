"""The workers' Celery app with faults injected from the environment, for tests/test_worker_faults.py only.

FAULT_CHUNK_SECONDS: every chunk sleeps this long before it scores, so that a test can kill it mid-chunk.
FAULT_POISON_TOKEN: a chunk holding this token kills its own process (SIGKILL), as a segfault or the
kernel's out-of-memory killer would, every time.
FAULT_HANG_TOKEN: a chunk holding this token hangs where Celery's soft time limit cannot interrupt it
(as C code that never returns to Python), so only the hard time limit stops it.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Sequence
from typing import Any

import worker.tasks
from worker.app import app

__all__ = ["app"]
_score_seeds = worker.tasks.score_seeds


def _faulty_score_seeds(
    split_dir: Any,
    cache_dir: Any,
    seeds: Any,
    versions: Sequence[str],
    tokens: Sequence[str],
    context: Sequence[str] = (),
) -> Any:
    if os.environ.get("FAULT_POISON_TOKEN") in tokens:
        os.kill(os.getpid(), signal.SIGKILL)
    if os.environ.get("FAULT_HANG_TOKEN") in tokens:
        signal.signal(signal.SIGUSR1, signal.SIG_IGN)  # Celery's soft time limit arrives as SIGUSR1
        while True:
            time.sleep(1)
    time.sleep(float(os.environ.get("FAULT_CHUNK_SECONDS", "0")))
    return _score_seeds(split_dir, cache_dir, seeds, versions, tokens, context=context)


worker.tasks.score_seeds = _faulty_score_seeds
