"""The one door from the API to the workers: send a submission's scoring task by name (the worker owns the task)."""

from __future__ import annotations

from typing import Any

from celery import Celery
from kombu.exceptions import ChannelError
from sqlalchemy import create_engine, inspect, text
from sqlalchemy.exc import OperationalError
from sqlalchemy.pool import NullPool

from server.settings import Settings, get_settings

SCORE_TASK = "worker.tasks.score_submission"
SQLITE_BROKER_TIMEOUT_S = 30.0
PRUNE_LOCK_WAIT_S = 2.0  # pruning is housekeeping: a file locked longer than this is pruned at a later pass
KOMBU_MESSAGE_TABLE = "kombu_message"  # kombu's default; we never set `message_tablename`
_clients: dict[tuple[str, str, float], Celery] = {}


def _embedded_broker_database(broker_url: str) -> str | None:
    """Return the SQLAlchemy URL of an embedded (kombu SQL transport) broker, None for any other broker."""
    scheme, _, rest = broker_url.partition("+")
    return rest if scheme in ("sqla", "sqlalchemy") and rest else None


def is_embedded_broker(settings: Settings) -> bool:
    """Whether the broker is the embedded one: kombu's SQL transport on a database file."""
    return _embedded_broker_database(settings.broker_url) is not None


def broker_transport_options(settings: Settings) -> dict[str, Any]:
    """Return the kombu transport options for the configured broker."""
    scheme = settings.broker_url.split("://", 1)[0]
    if is_embedded_broker(settings):
        # Every option reaches create_engine. No pool: a pooled SQLite connection must not cross a fork
        # into the worker's pool processes. The timeout lets writers queue instead of failing at once.
        return {"poolclass": NullPool, "connect_args": {"timeout": SQLITE_BROKER_TIMEOUT_S}}
    if scheme in ("redis", "rediss"):
        # An unacknowledged task is redelivered after this long: it must outlast the hard time limit of
        # the task it carries (plus the wait of a prefetched one), or a slow chunk would run twice at once.
        return {"visibility_timeout": 2 * settings.task_time_limit + 60}
    return {}


def celery_config(settings: Settings) -> dict[str, Any]:
    """Return the Celery settings the API (sender) and the workers share: broker, its options, the queue."""
    return {
        "broker_url": settings.broker_url,
        "broker_transport_options": broker_transport_options(settings),
        "broker_connection_retry_on_startup": True,
        "task_default_queue": settings.queue_name,
    }


def celery_client(settings: Settings) -> Celery:
    """Return a Celery app used only to send tasks to the configured broker and queue."""
    key = (settings.broker_url, settings.queue_name, settings.task_time_limit)
    if key not in _clients:
        client = Celery("navsim-lb-api")
        client.conf.update(celery_config(settings))
        _clients[key] = client
    return _clients[key]


def enqueue_submission(submission_id: int, settings: Settings | None = None) -> None:
    """Ask a worker to score the current run of a submission."""
    celery_client(settings or get_settings()).send_task(SCORE_TASK, args=[submission_id])


def waiting_tasks(settings: Settings, declare: bool = False) -> int:
    """Return how many tasks wait in the queue (taken by no worker); with `declare`, declare the queue and its
    binding again first.

    A broker that lost its state (Redis flushed) keeps the connections, so nobody declares again what
    each connection declared once, and kombu's Redis transport drops a message sent to an exchange with
    no binding: the reaper declares at every pass, which makes such a broker route again. Without
    `declare` (a Prometheus scrape) nothing changes on the broker: a queue it does not know holds 0 tasks.
    """
    client = celery_client(settings)
    queue = client.amqp.queues[settings.queue_name]
    with client.connection_for_write() as connection:
        bound = queue.bind(connection.default_channel)
        if declare:
            bound.declare()
        try:
            _, count, _ = bound.queue_declare(passive=not declare)
        except ChannelError:  # passive: the broker has no such queue (Redis drops an empty one's key)
            return 0
    return int(count)


def prune_embedded_broker(settings: Settings) -> int:
    """Delete the messages the embedded broker handed out already; return how many.

    kombu's SQL transport only hides a message it delivers (it has no acknowledgement to wait for), so
    without this its file grows with every task ever sent. Other brokers delete messages themselves.
    A file another process keeps locked for PRUNE_LOCK_WAIT_S is left as it is (0): the messages wait for a
    later pass, and the caller's work does not wait on them.
    """
    database = _embedded_broker_database(settings.broker_url)
    if database is None:
        return 0
    engine = create_engine(database, poolclass=NullPool, connect_args={"timeout": PRUNE_LOCK_WAIT_S})
    try:
        with engine.begin() as connection:
            if not inspect(connection).has_table(KOMBU_MESSAGE_TABLE):
                return 0
            deleted = connection.execute(text(f"DELETE FROM {KOMBU_MESSAGE_TABLE} WHERE visible = 0"))
            return deleted.rowcount
    except OperationalError as error:
        if "database is locked" in str(error.orig):
            return 0
        raise
    finally:
        engine.dispose()


def broker_status(settings: Settings) -> dict[str, Any]:
    """Return whether the broker accepts a connection, with the error when it does not."""
    try:
        with celery_client(settings).connection_for_write() as connection:
            connection.ensure_connection(max_retries=1, timeout=2)
    except Exception as error:  # noqa: BLE001 - any failure means "broker down", reported as text
        return {"ok": False, "detail": f"{type(error).__name__}: {error}"}
    return {"ok": True, "detail": ""}


def live_workers(settings: Settings) -> dict[str, Any]:
    """Return the workers answering a ping; `ok` is None when the transport cannot broadcast (embedded broker)."""
    app = celery_client(settings)
    try:
        with app.connection_for_read() as connection:
            can_broadcast = "fanout" in connection.transport.implements.exchange_type
            if not can_broadcast:
                return {
                    "ok": None,
                    "count": None,
                    "names": [],
                    "detail": "the broker cannot broadcast a ping",
                }
            replies = app.control.ping(timeout=1.0, connection=connection) or []
    except Exception as error:  # noqa: BLE001 - reported as text, health must answer
        return {
            "ok": False,
            "count": 0,
            "names": [],
            "detail": f"cannot ping workers: {type(error).__name__}: {error}",
        }
    names = sorted(name for reply in replies for name in reply)
    return {
        "ok": bool(names),
        "count": len(names),
        "names": names,
        "detail": "" if names else "no worker answered",
    }
