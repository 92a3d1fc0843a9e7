"""The human futures of a split are computed once per split and engine, then read by every worker: from its
cache directory, else from the object store another worker published them to; a damaged or foreign copy is
ignored and computed again. (A process keeps nothing in memory: a cache directory is a machine.)"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from object_stores import fresh_s3_store
from server_testing import REFERENCE_DIR

from scorer.human import human_future_poses, is_synthetic
from scorer.scene import load_scene, scene_paths
from server import shared_futures
from server.object_store import LocalStore, ObjectStore
from server.shared_caches import engine_key

SPLIT_HASH = "a" * 64


@pytest.fixture
def computed(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Count the futures computed from scenes (each call appends how many scenes it read)."""
    counts: list[int] = []
    compute = shared_futures.compute_futures

    def counting(scenes: dict[str, Path]) -> dict[str, np.ndarray]:
        counts.append(len(scenes))
        return compute(scenes)

    monkeypatch.setattr(shared_futures, "compute_futures", counting)
    return counts


def _expected() -> dict[str, np.ndarray]:
    return {
        token: human_future_poses(load_scene(scene))[:, :2]
        for token, scene in scene_paths(REFERENCE_DIR).items()
        if not is_synthetic(token)
    }


def _same(futures: dict[str, np.ndarray], expected: dict[str, np.ndarray]) -> bool:
    return list(futures) == list(expected) and all(
        futures[token].tobytes() == expected[token].tobytes() for token in expected
    )


@pytest.mark.parametrize("kind", ["local", "s3"])
def test_two_workers_sharing_a_store_compute_a_split_s_futures_once(
    tmp_path: Path, computed: list[int], kind: str
) -> None:
    store: ObjectStore = LocalStore(tmp_path / "store") if kind == "local" else fresh_s3_store()
    expected = _expected()
    first = shared_futures.human_futures(REFERENCE_DIR, SPLIT_HASH, tmp_path / "one", store)
    again = shared_futures.human_futures(REFERENCE_DIR, SPLIT_HASH, tmp_path / "one", store)
    other = shared_futures.human_futures(REFERENCE_DIR, SPLIT_HASH, tmp_path / "two", store)
    assert computed == [len(expected)]
    assert all(_same(futures, expected) for futures in (first, again, other))
    assert store.keys("human-futures/") == [f"human-futures/{engine_key()}/{SPLIT_HASH}.npz"]
    # Another split's content is another name: its futures are its own.
    shared_futures.human_futures(REFERENCE_DIR, "b" * 64, tmp_path / "two", store)
    assert computed == [len(expected)] * 2


def test_without_a_store_the_cache_directory_keeps_them(tmp_path: Path, computed: list[int]) -> None:
    for _ in range(2):
        futures = shared_futures.human_futures(REFERENCE_DIR, SPLIT_HASH, tmp_path / "cache", None)
    assert len(computed) == 1 and _same(futures, _expected())


def test_a_damaged_or_foreign_copy_is_computed_again(
    tmp_path: Path, computed: list[int], caplog: pytest.LogCaptureFixture
) -> None:
    store = LocalStore(tmp_path / "store")
    key = f"human-futures/{engine_key()}/{SPLIT_HASH}.npz"
    store.put_bytes(key, b"not an npz")
    with caplog.at_level(logging.WARNING, logger="server.shared_futures"):
        futures = shared_futures.human_futures(REFERENCE_DIR, SPLIT_HASH, tmp_path / "one", store)
    assert "damaged or foreign" in caplog.text and len(computed) == 1 and _same(futures, _expected())
    # A local file of another split's tokens (one dropped) is not taken for this split's.
    local = tmp_path / "two" / key
    local.parent.mkdir(parents=True)
    stored = np.load(tmp_path / "one" / key)
    np.savez(local, tokens=stored["tokens"][1:], positions=stored["positions"][1:])
    futures = shared_futures.human_futures(REFERENCE_DIR, SPLIT_HASH, tmp_path / "two", None)
    assert len(computed) == 2 and _same(futures, _expected())
