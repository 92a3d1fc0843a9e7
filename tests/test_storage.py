"""Content-addressed submission storage: an intact copy is kept, a damaged one is replaced by a new upload; the
parsed trajectories beside a file read back exactly, or not at all."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from server.storage import TRAJECTORIES_SUFFIX, read_file, read_trajectories, store_file, store_trajectories


def test_a_damaged_stored_copy_is_replaced_when_the_same_file_is_uploaded_again(tmp_path: Path) -> None:
    data = b'{"format": "navsim-lb/submission"}'
    sha256 = hashlib.sha256(data).hexdigest()
    name = store_file(tmp_path, sha256, data)
    assert read_file(tmp_path, name) == data
    (tmp_path / name).write_bytes(data[:10])  # a disk fault truncates it
    assert store_file(tmp_path, sha256, data) == name
    assert read_file(tmp_path, name) == data


def test_an_intact_copy_is_not_written_again(tmp_path: Path) -> None:
    data = b"same bytes"
    sha256 = hashlib.sha256(data).hexdigest()
    name = store_file(tmp_path, sha256, data)
    inode = (tmp_path / name).stat().st_ino
    assert store_file(tmp_path, sha256, data) == name
    assert (tmp_path / name).stat().st_ino == inode  # os.replace would have made a new file
    assert [path.name for path in (tmp_path / name).parent.iterdir()] == [sha256]  # no temporary left


def _trajectories() -> tuple[dict[str, np.ndarray], ...]:
    rng = np.random.default_rng(5)
    return tuple({f"token{i:03d}": rng.normal(size=(8, 3)) for i in range(seed, 40)} for seed in range(3))


def test_the_parsed_trajectories_read_back_bit_for_bit(tmp_path: Path) -> None:
    seeds = _trajectories()
    seeds[0]["token000"][0, 0] = -0.0
    store_trajectories(tmp_path, "ab/abc", "abc", seeds)
    read = read_trajectories(tmp_path, "ab/abc", "abc")
    assert read is not None and len(read) == 3
    for stored, written in zip(read, seeds, strict=True):
        assert list(stored) == list(written)  # the tokens, in their order
        assert all(stored[t].tobytes() == written[t].tobytes() and stored[t].shape == (8, 3) for t in written)


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")  # a file left open
def test_a_missing_damaged_or_foreign_copy_is_not_read(tmp_path: Path) -> None:
    assert read_trajectories(tmp_path, "ab/abc", "abc") is None
    store_trajectories(tmp_path, "ab/abc", "abc", _trajectories())
    assert read_trajectories(tmp_path, "ab/abc", "another sha256") is None
    path = tmp_path / "ab" / f"abc{TRAJECTORIES_SUFFIX}"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # a flipped bit inside the poses
    path.write_bytes(bytes(data))
    assert read_trajectories(tmp_path, "ab/abc", "abc") is None
    path.write_bytes(bytes(data[:100]))
    assert read_trajectories(tmp_path, "ab/abc", "abc") is None
