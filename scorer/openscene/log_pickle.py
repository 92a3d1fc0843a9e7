"""Load an OpenScene log pickle without executing anything beyond numpy array reconstruction.

Log pickles are trusted organiser files, but a log is still only data: the unpickler resolves the
few numpy globals a list of frame dicts needs (upstream-formats.md 1.1) and refuses every other one.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any

import numpy as np
from numpy._core import multiarray, numeric

from scorer.submission import UNPICKLING_ERRORS

# numpy < 2 writers name `numpy.core.*`, numpy >= 2 writers `numpy._core.*`; both map to the same code.
NUMPY_GLOBALS: dict[tuple[str, str], Any] = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    # A private numpy function, which the devkit's pickles of arrays name.
    **{(f"numpy.{core}.numeric", "_frombuffer"): numeric._frombuffer for core in ("core", "_core")},  # type: ignore[attr-defined]
    **{(f"numpy.{core}.multiarray", "_reconstruct"): multiarray._reconstruct for core in ("core", "_core")},
    **{(f"numpy.{core}.multiarray", "scalar"): multiarray.scalar for core in ("core", "_core")},
}


class LogFormatError(ValueError):
    """A log pickle cannot be read as a list of OpenScene frame dicts; the message names the file."""


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that resolves only the globals of `allowed` and refuses persistent ids."""

    def __init__(self, data: bytes, allowed: dict[tuple[str, str], Any], what: str) -> None:
        super().__init__(io.BytesIO(data))
        self.allowed = allowed
        self.what = what

    def find_class(self, module: str, name: str) -> Any:
        try:
            return self.allowed[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"global {module}.{name} is not allowed in {self.what}") from None

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError("persistent ids are not allowed")


def load_log(path: Path | str) -> list[dict[str, Any]]:
    """Return the frame dicts of an OpenScene log pickle, in file (time) order."""
    path = Path(path)
    try:
        frames = RestrictedUnpickler(path.read_bytes(), NUMPY_GLOBALS, "a log pickle").load()
    except UNPICKLING_ERRORS as error:
        raise LogFormatError(f"{path}: not a readable log pickle ({error})") from None
    if not isinstance(frames, list) or not all(isinstance(frame, dict) for frame in frames):
        raise LogFormatError(f"{path}: expected a list of frame dicts, got {type(frames).__name__}")
    return frames
