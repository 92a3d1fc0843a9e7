"""Every log line of a worker names the submission and run it concerns, as fields: `submission=12 run=3`.

A task's arguments start with the submission id (and, for a chunk, the run): `task_prerun` puts them in a
context variable, the record factory copies them onto each record, and the worker's log formats print them,
so `grep 'submission=12 '` finds all that happened to one submission, across processes and machines.
The factory, not a handler's filter, because Celery gives billiard's logger a handler of its own with the
same format: a record of it without the fields (a pool process that died) would fail to format.
"""

from __future__ import annotations

import logging
from contextvars import ContextVar
from typing import Any

from celery.signals import task_postrun, task_prerun

UNKNOWN = "-"
FIELDS = "submission=%(submission)s run=%(run)s"
LOG_FORMAT = f"[%(asctime)s: %(levelname)s/%(processName)s] {FIELDS} %(message)s"
TASK_LOG_FORMAT = (
    f"[%(asctime)s: %(levelname)s/%(processName)s] {FIELDS} %(task_name)s[%(task_id)s]: %(message)s"
)
_scoring_run: ContextVar[tuple[Any, Any]] = ContextVar("scoring_run", default=(UNKNOWN, UNKNOWN))


_plain_record = logging.getLogRecordFactory()


def _record_with_run(*args: Any, **kwargs: Any) -> logging.LogRecord:
    """Return a log record with `submission` and `run` set (UNKNOWN outside a scoring task)."""
    record = _plain_record(*args, **kwargs)
    record.submission, record.run = _scoring_run.get()
    return record


logging.setLogRecordFactory(_record_with_run)


@task_prerun.connect
def _enter_task(args: tuple[Any, ...] | None = None, **_: object) -> None:
    submission = args[0] if args else UNKNOWN
    run = args[1] if args and len(args) > 1 else UNKNOWN
    _scoring_run.set((submission, run))


@task_postrun.connect
def _leave_task(**_: object) -> None:
    _scoring_run.set((UNKNOWN, UNKNOWN))
