"""Throwaway PostgreSQL databases and Redis queues for the tests and benchmarks that run on real servers."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from contextlib import contextmanager

import redis
from sqlalchemy import create_engine, text


@contextmanager
def scratch_postgres_database(server_url: str, prefix: str) -> Iterator[str]:
    """Create an empty database named `prefix` + a random suffix on the server of `server_url`; yield its URL.

    The database is dropped afterwards, even with connections still open (a killed worker's).
    """
    name = f"{prefix}_{uuid.uuid4().hex[:12]}"
    admin = create_engine(server_url, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as connection:
            connection.execute(text(f'CREATE DATABASE "{name}"'))
        try:
            yield server_url.rsplit("/", 1)[0] + f"/{name}"
        finally:
            with admin.connect() as connection:
                connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    finally:
        admin.dispose()


@contextmanager
def scratch_redis_queue(redis_url: str, prefix: str) -> Iterator[str]:
    """Yield a queue name of its own (`prefix` + a random suffix); delete every Redis key naming it afterwards."""
    queue = f"{prefix}-{uuid.uuid4().hex[:12]}"
    try:
        yield queue
    finally:
        broker = redis.Redis.from_url(redis_url)
        leftovers = broker.keys(f"*{queue}*")
        if leftovers:
            broker.delete(*leftovers)
        broker.close()
