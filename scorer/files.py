"""Writing a file so that readers see the old content or the new, never a part: a temporary file, a rename."""

from __future__ import annotations

import os
from pathlib import Path

_TEMPORARY_ATTEMPTS = 100  # names tried before giving up, as tempfile.mkstemp does (its TMP_MAX is larger)


def create_temporary_beside(path: Path) -> tuple[int, str]:
    """Create a new empty file `.<name>.<random>.partial` in `path`'s directory, readable and writable by its
    owner only; return its descriptor and its name.

    What `tempfile.mkstemp` does (a random name, created exclusively, retried on a clash), without importing
    tempfile and `random`: a millisecond of a one-token `navsim-lb score --out`.
    """
    for _ in range(_TEMPORARY_ATTEMPTS):
        name = str(path.parent / f".{path.name}.{os.urandom(6).hex()}.partial")
        try:
            return os.open(
                name, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600
            ), name
        except FileExistsError:
            continue
    raise FileExistsError(f"no unused temporary name beside {path}")


def write_atomically(path: Path, data: bytes, durable: bool = True) -> None:
    """Write `data` to `path` through a temporary file in the same directory and a rename.

    `durable` also flushes the bytes to the disk before the rename, so that a crash cannot leave an empty
    file under the name: needed for what cannot be made again (uploads), not for what is rebuilt when
    missing (metric caches, imported scenes), where it would only cost time.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = create_temporary_beside(path)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            if durable:
                handle.flush()
                os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
