"""Content-addressed submission storage on both backends (a directory, and S3 on CI's moto server): a file
reads back as stored, an intact local copy is kept, a damaged one is replaced by a new upload; the parsed
trajectories beside a file read back exactly, or not at all."""

from __future__ import annotations

import hashlib
import io
from pathlib import Path

import numpy as np
import pytest
from object_stores import fresh_s3_store

from server.object_store import LocalStore, ObjectStore
from server.storage import TRAJECTORIES_SUFFIX, read_file, read_trajectories, store_file, store_trajectories


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> ObjectStore:
    return LocalStore(tmp_path) if request.param == "local" else fresh_s3_store()


def _stored(store: ObjectStore, data: bytes) -> str:
    return store_file(store, hashlib.sha256(data).hexdigest(), io.BytesIO(data))


def test_a_stored_file_reads_back_under_its_sha256(store: ObjectStore) -> None:
    data = b'{"format": "navsim-lb/submission"}'
    name = _stored(store, data)
    assert name == f"{hashlib.sha256(data).hexdigest()[:2]}/{hashlib.sha256(data).hexdigest()}"
    assert read_file(store, name) == data
    with pytest.raises(FileNotFoundError):
        read_file(store, "00/missing")


def test_a_damaged_stored_copy_is_replaced_when_the_same_file_is_uploaded_again(tmp_path: Path) -> None:
    data = b'{"format": "navsim-lb/submission"}'
    name = _stored(LocalStore(tmp_path), data)
    (tmp_path / name).write_bytes(data[:10])  # a disk fault truncates it
    assert _stored(LocalStore(tmp_path), data) == name
    assert read_file(LocalStore(tmp_path), name) == data


def test_an_intact_copy_is_not_written_again(tmp_path: Path) -> None:
    data = b"same bytes"
    name = _stored(LocalStore(tmp_path), data)
    inode = (tmp_path / name).stat().st_ino
    assert _stored(LocalStore(tmp_path), data) == name
    assert (tmp_path / name).stat().st_ino == inode  # os.replace would have made a new file
    assert [path.name for path in (tmp_path / name).parent.iterdir()] == [name.split("/")[1]]  # no temporary


def _trajectories() -> tuple[dict[str, np.ndarray], ...]:
    rng = np.random.default_rng(5)
    return tuple({f"token{i:03d}": rng.normal(size=(8, 3)) for i in range(seed, 40)} for seed in range(3))


def test_the_parsed_trajectories_read_back_bit_for_bit(store: ObjectStore) -> None:
    seeds = _trajectories()
    seeds[0]["token000"][0, 0] = -0.0
    store_trajectories(store, "ab/abc", "abc", seeds)
    read = read_trajectories(store, "ab/abc", "abc")
    assert read is not None and len(read) == 3
    for stored, written in zip(read, seeds, strict=True):
        assert list(stored) == list(written)  # the tokens, in their order
        assert all(stored[t].tobytes() == written[t].tobytes() and stored[t].shape == (8, 3) for t in written)


def test_a_missing_damaged_or_foreign_copy_is_not_read(store: ObjectStore) -> None:
    assert read_trajectories(store, "ab/abc", "abc") is None
    store_trajectories(store, "ab/abc", "abc", _trajectories())
    assert read_trajectories(store, "ab/abc", "another sha256") is None
    key = f"ab/abc{TRAJECTORIES_SUFFIX}"
    data = bytearray(store.get(key))
    data[len(data) // 2] ^= 0xFF  # a flipped bit inside the poses
    store.put_bytes(key, bytes(data))
    assert read_trajectories(store, "ab/abc", "abc") is None
    store.put_bytes(key, bytes(data[:100]))
    assert read_trajectories(store, "ab/abc", "abc") is None
