"""The broker side of server.queue: the embedded broker's file keeps only messages not yet delivered."""

from __future__ import annotations

from pathlib import Path

from kombu import Connection

from server.queue import celery_client, prune_embedded_broker
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


def test_pruning_leaves_other_brokers_alone(tmp_path: Path) -> None:
    settings = Settings(DATA_DIR=tmp_path, BROKER_URL="redis://127.0.0.1:1/0")  # never contacted
    assert prune_embedded_broker(settings) == 0
