"""Writing a file so that readers see the old content or the new, never a part: a temporary file, a rename."""

from __future__ import annotations

import os
from pathlib import Path


def write_atomically(path: Path, data: bytes, durable: bool = True) -> None:
    """Write `data` to `path` through a temporary file in the same directory and a rename.

    `durable` also flushes the bytes to the disk before the rename, so that a crash cannot leave an empty
    file under the name: needed for what cannot be made again (uploads), not for what is rebuilt when
    missing (metric caches, imported scenes), where it would only cost time.
    """
    import tempfile  # here, not above: a `navsim-lb score` that writes nothing never pays for its import

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".partial")
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
