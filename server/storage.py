"""Submission files on disk, content-addressed by sha256 (so a retried upload never writes a second copy)."""

from __future__ import annotations

import hashlib
from pathlib import Path

from scorer.files import write_atomically


def stored_name(sha256: str) -> str:
    """Return the storage-relative name of a file with this sha256."""
    return f"{sha256[:2]}/{sha256}"


def _holds(path: Path, sha256: str) -> bool:
    """Return whether the file at `path` exists and its content hashes to `sha256`."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest() == sha256
    except OSError:
        return False


def store_file(storage_dir: Path, sha256: str, data: bytes) -> str:
    """Write `data` atomically under its sha256 and return its stored name. An intact copy is kept as it is;
    a damaged one (its bytes no longer hash to its name) is replaced, so uploading the file again repairs it."""
    name = stored_name(sha256)
    path = Path(storage_dir) / name
    if _holds(path, sha256):
        return name
    write_atomically(path, data)
    return name


def read_file(storage_dir: Path, name: str) -> bytes:
    """Return the bytes of a stored submission file."""
    return (Path(storage_dir) / name).read_bytes()
