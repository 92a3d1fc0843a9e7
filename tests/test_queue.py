"""The broker side of server.queue: the embedded broker's file keeps only messages not yet delivered; counting
the waiting tasks changes nothing on the broker unless the reaper asks it to declare the queue again."""

from __future__ import annotations

import os
import sqlite3
import time
from pathlib import Path

import pytest
import redis
from kombu import Connection
from scratch import scratch_redis_queue

from server.queue import (
    SCORE_TASK,
    SQLITE_BROKER_TIMEOUT_S,
    celery_client,
    prune_embedded_broker,
    waiting_tasks,
)
from server.settings import Settings


def test_pruning_deletes_delivered_messages_and_keeps_waiting_ones(tmp_path: Path) -> None:
    settings = Settings(DATA_DIR=tmp_path)
    assert prune_embedded_broker(settings) == 0  # no broker file yet: nothing to do, no error
    sender = celery_client(settings)
    for number in range(3):
        sender.send_task("worker.tasks.score_submission", args=[number])
    with Connection(settings.broker_url) as connection:
        queue = connection.SimpleQueue(settings.queue_name)
        delivered = [queue.get(timeout=5) for _ in range(2)]
        for message in delivered:
            message.ack()
        assert prune_embedded_broker(settings) == 2
        assert prune_embedded_broker(settings) == 0
        waiting = queue.get(timeout=5)
        assert waiting.headers["argsrepr"] == "[2]"
        queue.close()


def test_pruning_leaves_a_file_another_process_keeps_locked_for_a_later_pass(tmp_path: Path) -> None:
    settings = Settings(DATA_DIR=tmp_path)
    celery_client(settings).send_task("worker.tasks.score_submission", args=[1])
    with Connection(settings.broker_url) as connection:
        queue = connection.SimpleQueue(settings.queue_name)
        queue.get(timeout=5).ack()
        queue.close()
    holder = sqlite3.connect(tmp_path / "broker.sqlite", isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")  # as a process stuck inside a write would hold it
    try:
        started = time.monotonic()
        assert prune_embedded_broker(settings) == 0
        # It gave up long before a broker write would have.
        assert time.monotonic() - started < SQLITE_BROKER_TIMEOUT_S
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    assert prune_embedded_broker(settings) == 1  # the next pass prunes it


def test_pruning_leaves_other_brokers_alone(tmp_path: Path) -> None:
    settings = Settings(DATA_DIR=tmp_path, BROKER_URL="redis://127.0.0.1:1/0")  # never contacted
    assert prune_embedded_broker(settings) == 0


@pytest.mark.services
def test_counting_waiting_tasks_declares_nothing_unless_asked(tmp_path: Path) -> None:
    url = os.environ.get("NAVSIM_LB_TEST_REDIS", "redis://127.0.0.1:6379/0")
    broker = redis.Redis.from_url(url)
    with scratch_redis_queue(url, "navsim-lb-count") as queue:
        settings = Settings(data_dir=tmp_path, broker_url=url, queue_name=queue)
        binding = f"_kombu.binding.{queue}"
        assert waiting_tasks(settings) == 0  # an unknown queue holds nothing
        assert not broker.exists(binding)  # and a scrape did not create it
        assert waiting_tasks(settings, declare=True) == 0
        assert broker.exists(binding)  # the reaper's pass declares the queue and its binding
        celery_client(settings).send_task(SCORE_TASK, args=[1], queue=queue)
        assert waiting_tasks(settings) == 1
    broker.close()
