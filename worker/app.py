"""The workers' Celery app, configured from `server.settings` with the broker and queue the API sends to.

Each consumer is one process running one task at a time (`--pool solo`, under worker.supervisor, which sets
its priority and BLAS threads, and keeps the time limits from what the consumer reports here). Delivery is at
least once: a task is acknowledged after it ran (`acks_late`) and the broker's visibility timeout outlasts
the hard time limit (server.queue); the reaper (worker.reaper) sends again what a dead process held. Every
task is therefore idempotent.
No result backend: results live in SQL (worker.tasks explains why no chord is needed).
"""

from __future__ import annotations

from typing import ClassVar

from celery import Celery, Task, bootsteps
from celery.signals import task_postrun, task_prerun, worker_ready

from server.queue import celery_config
from server.settings import Settings, get_settings
from worker.heartbeat import DatabaseHeartbeat
from worker.logs import LOG_FORMAT, TASK_LOG_FORMAT
from worker.supervised import become_supervised, report_busy, report_idle

CHUNK_TASK = "worker.tasks.score_chunk"
INTEGRITY_TASK = "worker.tasks.check_integrity"
SOFT_LIMIT_MARGIN_S = 30.0
EMBEDDED_POLL_S = 0.1


def chunk_soft_time_limit(settings: Settings) -> float:
    """Return the soft time limit of a chunk: it stops itself and fails its run cleanly before the hard limit."""
    return settings.task_time_limit - SOFT_LIMIT_MARGIN_S


@worker_ready.connect
def _take_the_supervisors_limits(**_: object) -> None:
    become_supervised()  # after Celery's own handlers: its SIGUSR1 one logs stacks, ours is the soft limit


@task_prerun.connect
def _report_task(task: Task, **_: object) -> None:
    report_busy(task.name, task.soft_time_limit, task.time_limit or task.app.conf.task_time_limit)


@task_postrun.connect
def _report_done(**_: object) -> None:
    report_idle()


class EmbeddedBrokerPolling(bootsteps.StartStopStep):
    """Poll the embedded SQL broker every 0.1 s instead of kombu's default 1 s.

    With one task reserved per process, a worker only asks for the next task after the last one ended,
    and an empty answer costs a full polling interval: at 1 s that is most of a one-second chunk.
    """

    requires: ClassVar[set[str]] = {"celery.worker.consumer.connection:Connection"}

    def start(self, parent: object) -> None:
        transport = parent.connection.transport  # type: ignore[attr-defined]
        if transport.driver_type == "sql":
            transport.polling_interval = EMBEDDED_POLL_S


def create_celery(settings: Settings) -> Celery:
    """Return the workers' Celery app for `settings`."""
    # The embedded broker's SQLite file lives there, and kombu does not create the directory.
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    app = Celery("navsim-lb", include=["worker.tasks"])
    app.conf.update(
        celery_config(settings),
        task_acks_late=True,
        worker_prefetch_multiplier=1,
        # The supervisor (worker.supervisor) keeps both limits: the solo pool keeps none.
        task_time_limit=settings.task_time_limit,
        # Only scoring a chunk has a soft limit. It arrives as an exception raised wherever the task is: in
        # planning, that is inside a broker write, which can leave the embedded broker's file locked by the
        # process for every other one. The hard limit kills the process, which frees it.
        # A split's integrity check reads every entry, and the first one its scenes' human futures too (minutes
        # on navtest): twice a chunk's hard limit, still under the broker's redelivery timeout (server.queue).
        task_annotations={
            CHUNK_TASK: {"soft_time_limit": chunk_soft_time_limit(settings)},
            INTEGRITY_TASK: {"time_limit": 2 * settings.task_time_limit},
        },
        task_ignore_result=True,
        worker_log_format=LOG_FORMAT,
        worker_task_log_format=TASK_LOG_FORMAT,
    )
    app.steps["consumer"].add(EmbeddedBrokerPolling)
    app.steps["consumer"].add(DatabaseHeartbeat)
    return app


app = create_celery(get_settings())
