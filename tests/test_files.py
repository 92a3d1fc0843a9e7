"""Atomic writes: a temporary file beside the target, created exclusively, renamed over it or removed."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from scorer import files
from scorer.files import create_temporary_beside, write_atomically


def test_a_temporary_file_is_new_private_and_hidden_beside_its_target(tmp_path: Path) -> None:
    target = tmp_path / "results.csv"
    fd, name = create_temporary_beside(target)
    os.close(fd)
    temporary = Path(name)
    assert temporary.parent == tmp_path and temporary.name.startswith(".results.csv.")
    assert temporary.name.endswith(".partial") and temporary.stat().st_size == 0
    assert stat.S_IMODE(temporary.stat().st_mode) == 0o600
    fd, other = create_temporary_beside(target)
    os.close(fd)
    assert other != name


def test_a_name_in_use_is_never_opened_again(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A clash (the same random part) tries another name; the file in the way is left as it was."""
    draws = iter([b"\x00" * 6, b"\x00" * 6, b"\x01" * 6])
    monkeypatch.setattr(files.os, "urandom", lambda size: next(draws))
    target = tmp_path / "entry.json"
    fd, first = create_temporary_beside(target)
    os.write(fd, b"kept")
    os.close(fd)
    fd, second = create_temporary_beside(target)
    os.close(fd)
    assert second != first and Path(first).read_bytes() == b"kept"


def test_an_atomic_write_leaves_the_file_and_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "deep" / "results.csv"
    write_atomically(target, b"old")
    write_atomically(target, b"new", durable=False)
    assert target.read_bytes() == b"new"
    assert [path.name for path in target.parent.iterdir()] == ["results.csv"]


def test_a_failed_write_removes_its_temporary_and_keeps_the_old_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = tmp_path / "results.csv"
    write_atomically(target, b"old")

    def failing_replace(source: str, destination: Path) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(files.os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        write_atomically(target, b"new")
    assert target.read_bytes() == b"old"
    assert [path.name for path in tmp_path.iterdir()] == ["results.csv"]
