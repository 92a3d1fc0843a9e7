"""Content-addressed submission storage: an intact copy is kept, a damaged one is replaced by a new upload."""

from __future__ import annotations

import hashlib
from pathlib import Path

from server.storage import read_file, store_file


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
