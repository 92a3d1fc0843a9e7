"""Every log line of a worker names the submission and run it concerns, as fields: `submission=12 run=3`.

A task's arguments start with the submission id (and, for a chunk, the run): `task_prerun` puts them in a
context variable, a logging filter copies them onto each record, and the worker's log formats print them,
so `grep 'submission=12 '` finds all that happened to one submission, across processes and machines.
"""

from __future__ import annotations

import logging
from contextvars import ContextVar
from typing import Any

from celery.signals import after_setup_logger, after_setup_task_logger, task_postrun, task_prerun

UNKNOWN = "-"
FIELDS = "submission=%(submission)s run=%(run)s"
LOG_FORMAT = f"[%(asctime)s: %(levelname)s/%(processName)s] {FIELDS} %(message)s"
TASK_LOG_FORMAT = (
    f"[%(asctime)s: %(levelname)s/%(processName)s] {FIELDS} %(task_name)s[%(task_id)s]: %(message)s"
)
_scoring_run: ContextVar[tuple[Any, Any]] = ContextVar("scoring_run", default=(UNKNOWN, UNKNOWN))


class RunFields(logging.Filter):
    """Set `submission` and `run` on every record (UNKNOWN outside a scoring task)."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.submission, record.run = _scoring_run.get()
        return True


@task_prerun.connect
def _enter_task(args: tuple[Any, ...] | None = None, **_: object) -> None:
    submission = args[0] if args else UNKNOWN
    run = args[1] if args and len(args) > 1 else UNKNOWN
    _scoring_run.set((submission, run))


@task_postrun.connect
def _leave_task(**_: object) -> None:
    _scoring_run.set((UNKNOWN, UNKNOWN))


@after_setup_logger.connect
@after_setup_task_logger.connect
def _add_fields(logger: logging.Logger, **_: object) -> None:
    for handler in logger.handlers:
        handler.addFilter(RunFields())
