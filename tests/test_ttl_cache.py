"""The board's cache under load: one computation at a time per key, the stale value served meanwhile."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from server.ttl_cache import TTLCache


def test_concurrent_misses_of_a_key_compute_it_once() -> None:
    cache: TTLCache[int] = TTLCache(60)
    calls = []

    def compute() -> int:
        calls.append(1)
        time.sleep(0.2)
        return 42

    with ThreadPoolExecutor(16) as pool:
        values = list(pool.map(lambda _: cache.get_or_compute("board", compute), range(16)))
    assert values == [42] * 16
    assert len(calls) == 1


def test_an_expired_value_is_served_while_one_caller_computes_the_next() -> None:
    cache: TTLCache[str] = TTLCache(0.05)
    cache.put("board", "old")
    time.sleep(0.1)
    assert cache.get("board") is None  # expired
    started, release = threading.Event(), threading.Event()

    def slow() -> str:
        started.set()
        release.wait(5)
        return "new"

    with ThreadPoolExecutor(1) as pool:
        computing = pool.submit(cache.get_or_compute, "board", slow)
        assert started.wait(5)
        # Another caller meanwhile gets the stale value at once, and does not compute.
        assert cache.get_or_compute("board", lambda: pytest.fail("computed twice")) == "old"
        release.set()
        assert computing.result(5) == "new"
    assert cache.get("board") == "new"


def test_an_error_reaches_its_caller_only_and_the_next_caller_computes_again() -> None:
    cache: TTLCache[str] = TTLCache(60)

    def broken() -> str:
        raise RuntimeError("database away")

    with pytest.raises(RuntimeError, match="database away"):
        cache.get_or_compute("board", broken)
    assert cache.get_or_compute("board", lambda: "back") == "back"
    assert cache.get("board") == "back"


def test_with_caching_off_every_call_computes() -> None:
    cache: TTLCache[int] = TTLCache(0)
    counter = iter(range(10))
    assert [cache.get_or_compute("board", lambda: next(counter)) for _ in range(3)] == [0, 1, 2]


def test_evicted_keys_leave_nothing_behind() -> None:
    cache: TTLCache[int] = TTLCache(60, max_entries=2)
    for key in range(5):
        cache.get_or_compute(key, lambda key=key: key)  # type: ignore[misc]
    assert [cache.get(key) for key in range(5)] == [None, None, None, 3, 4]
    assert set(cache._computing) == {3, 4}
