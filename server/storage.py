"""Submission files on disk, content-addressed by sha256 (so a retried upload never writes a second copy).

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
from pathlib import Path
from typing import Any

import numpy as np

from scorer.files import write_atomically
from scorer.geometry import FloatArray

TRAJECTORIES_SUFFIX = ".npz"


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


def _trajectories_path(storage_dir: Path, name: str) -> Path:
    return Path(storage_dir) / f"{name}{TRAJECTORIES_SUFFIX}"


def store_trajectories(
    storage_dir: Path, name: str, sha256: str, seeds: Sequence[Mapping[str, FloatArray]]
) -> None:
    """Write the parsed trajectories of the stored file `name` (whose bytes hash to `sha256`) beside it."""
    arrays: dict[str, Any] = {"sha256": np.array(sha256)}
    for seed, predictions in enumerate(seeds):
        arrays[f"tokens_{seed}"] = np.array(list(predictions), dtype=str)
        arrays[f"poses_{seed}"] = np.array(list(predictions.values()), dtype=np.float64)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    # Not durable: a copy lost in a crash is only parsed again.
    write_atomically(_trajectories_path(storage_dir, name), buffer.getvalue(), durable=False)


def read_trajectories(storage_dir: Path, name: str, sha256: str) -> tuple[dict[str, FloatArray], ...] | None:
    """Return each seed's token -> poses of the stored file `name` as parsed at upload, or None when there is no
    intact copy parsed from bytes hashing to `sha256`."""
    try:
        # Opened here, not by np.load: np.load leaves its own file open when the archive is damaged.
        with (
            _trajectories_path(storage_dir, name).open("rb") as file,
            np.load(file, allow_pickle=False) as stored,
        ):
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
    storage_dir: Path, name: str, sha256: str, filename: str
) -> tuple[dict[str, FloatArray], ...]:
    """Return each seed's token -> poses of a stored one-stage submission: the parsed copy, or else the file parsed
    again (an upload stored before the parsed copies, or a copy lost). Raises SubmissionError when it cannot be
    read as one."""
    from scorer.submission import load_submission

    seeds = read_trajectories(storage_dir, name, sha256)
    if seeds is None:
        seeds = load_submission(read_file(storage_dir, name), filename).seeds
    return seeds
