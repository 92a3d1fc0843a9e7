"""Submission files in the object store (server.object_store: a directory, or S3), content-addressed by sha256
(so a retried upload never writes a second copy).

Beside each file the server keeps its trajectories as the upload's check parsed them (`<name>.npz`: per seed,
its tokens and their poses as one array): a worker process and the picture of a token read them in
milliseconds, where parsing a navtest-size JSON file again takes 0.6-2 s. The copy names the file it was
parsed from; a missing, damaged (the zip's CRCs) or foreign copy is ignored, and the file is parsed instead.
"""

from __future__ import annotations

import hashlib
import io
import zipfile
from collections.abc import Mapping, Sequence
from typing import IO, Any

import numpy as np

from scorer.geometry import FloatArray
from server.object_store import LocalStore, MissingObject, ObjectStore

TRAJECTORIES_SUFFIX = ".npz"


def stored_name(sha256: str) -> str:
    """Return the storage-relative name of a file with this sha256."""
    return f"{sha256[:2]}/{sha256}"


def _holds(store: ObjectStore, name: str, sha256: str) -> bool:
    """Return whether a file on a local disk holds content hashing to `sha256`. An S3 object is never checked
    (it is read whole to hash): it is whole or absent, and its store keeps it intact."""
    if not isinstance(store, LocalStore):
        return False
    try:
        return hashlib.sha256(store.get(name)).hexdigest() == sha256
    except OSError:
        return False


def store_file(store: ObjectStore, sha256: str, source: IO[bytes]) -> str:
    """Store what `source` reads (streamed: multipart to S3) under its sha256 and return its stored name. An
    intact local copy is kept as it is; a damaged one (its bytes no longer hash to its name) is replaced, so
    uploading the file again repairs it. Raises StoreUnavailable when the store cannot take it."""
    name = stored_name(sha256)
    if not _holds(store, name, sha256):
        store.put(name, source)
    return name


def read_file(store: ObjectStore, name: str) -> bytes:
    """Return the bytes of a stored submission file (MissingObject, a FileNotFoundError, when it is gone)."""
    return store.get(name)


def store_trajectories(
    store: ObjectStore, name: str, sha256: str, seeds: Sequence[Mapping[str, FloatArray]]
) -> None:
    """Write the parsed trajectories of the stored file `name` (whose bytes hash to `sha256`) beside it."""
    arrays: dict[str, Any] = {"sha256": np.array(sha256)}
    for seed, predictions in enumerate(seeds):
        arrays[f"tokens_{seed}"] = np.array(list(predictions), dtype=str)
        arrays[f"poses_{seed}"] = np.array(list(predictions.values()), dtype=np.float64)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    store.put_bytes(f"{name}{TRAJECTORIES_SUFFIX}", buffer.getvalue())


def read_trajectories(store: ObjectStore, name: str, sha256: str) -> tuple[dict[str, FloatArray], ...] | None:
    """Return each seed's token -> poses of the stored file `name` as parsed at upload, or None when there is no
    intact copy parsed from bytes hashing to `sha256` (StoreUnavailable when the store cannot be reached)."""
    try:
        data = store.get(f"{name}{TRAJECTORIES_SUFFIX}")
    except MissingObject:
        return None
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as stored:
            if str(stored["sha256"]) != sha256:
                return None
            seeds = []
            for seed in range(sum(key.startswith("tokens_") for key in stored.files)):
                tokens, poses = stored[f"tokens_{seed}"].tolist(), stored[f"poses_{seed}"]
                seeds.append(dict(zip(tokens, poses, strict=True)))
            return tuple(seeds)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return None


def submission_trajectories(
    store: ObjectStore, name: str, sha256: str, filename: str
) -> tuple[dict[str, FloatArray], ...]:
    """Return each seed's token -> poses of a stored one-stage submission: the parsed copy, or else the file parsed
    again (an upload stored before the parsed copies, or a copy lost). Raises SubmissionError when it cannot be
    read as one."""
    from scorer.submission import load_submission

    seeds = read_trajectories(store, name, sha256)
    if seeds is None:
        seeds = load_submission(read_file(store, name), filename).seeds
    return seeds
