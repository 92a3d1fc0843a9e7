"""A small in-process cache with a time to live: the public leaderboard is read far more often than it changes.

Under load a cache must not stampede: when a board expires while 200 requests a second read it, each of them
computing it again would queue dozens of the same queries behind the workers' writes. So one caller at a time
computes a key (`get_or_compute`): while it does, the others are served the expired value if there is one
(stale while it revalidates, at most one computation's time), else they wait for its result.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

Value = TypeVar("Value")


class TTLCache(Generic[Value]):
    """Values are fresh for `ttl_seconds` after they were stored, and kept stale after that; at most
    `max_entries` are kept (oldest out first)."""

    def __init__(self, ttl_seconds: float, max_entries: int = 256) -> None:
        self.ttl_seconds = ttl_seconds
        self.max_entries = max_entries
        self._entries: OrderedDict[Hashable, tuple[float, Value]] = OrderedDict()
        self._computing: dict[Hashable, threading.Lock] = {}  # one per key being computed or kept
        self._lock = threading.Lock()

    def get(self, key: Hashable) -> Value | None:
        """Return the fresh value of `key`, or None."""
        with self._lock:
            entry = self._entries.get(key)
        return entry[1] if entry is not None and entry[0] > time.monotonic() else None

    def put(self, key: Hashable, value: Value) -> None:
        """Keep `value` under `key` for the time to live (a no-op when caching is off)."""
        if self.ttl_seconds <= 0:
            return
        with self._lock:
            self._entries[key] = (time.monotonic() + self.ttl_seconds, value)
            self._entries.move_to_end(key)
            while len(self._entries) > self.max_entries:
                evicted, _ = self._entries.popitem(last=False)
                self._computing.pop(evicted, None)

    def get_or_compute(self, key: Hashable, compute: Callable[[], Value]) -> Value:
        """Return the fresh value of `key`; else compute it, one caller at a time: the others meanwhile get the
        stale value, or wait for the computed one when there is none. An exception of `compute` reaches only
        its own caller."""
        if self.ttl_seconds <= 0:
            return compute()
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None and entry[0] > time.monotonic():
                return entry[1]
            computing = self._computing.setdefault(key, threading.Lock())
        if entry is not None and not computing.acquire(blocking=False):
            return entry[1]  # another caller is computing it
        if entry is None:
            computing.acquire()
            fresh = self.get(key)  # computed meanwhile by the caller this one waited for
            if fresh is not None:
                computing.release()
                return fresh
        try:
            value = compute()
            self.put(key, value)
            return value
        finally:
            computing.release()
            with self._lock:
                if key not in self._entries:  # never computed (an error): keys of bad queries are not kept
                    self._computing.pop(key, None)
