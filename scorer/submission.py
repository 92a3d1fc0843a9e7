"""Read submissions without trusting them: `navsim-lb/submission` JSON and NAVSIM's submission pickle.

The format is decided by the bytes, not the file name (NAVSIM pickles are often xz streams named
`.pkl`), and a file of another kind is named by them (zip, bzip2, text, ...). Compressed files are inflated as a
stream: refused as soon as their first bytes show neither JSON nor a pickle (compressed twice, say), or once
they pass what a valid submission of the split can take (ContentLimit), holding little of them in memory. Pickles are read by a restricted unpickler that maps the few globals a NAVSIM submission
holds to inert records and refuses every other one, so a hostile file can never execute code.
Every problem names the seed, token and field it is about; loading collects all of them.
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
import io
import json
import lzma
import math
import pickle
import re
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import IO, Any, NamedTuple, Protocol, cast

import numpy as np

from scorer.geometry import FloatArray

FORMAT = "navsim-lb/submission"
TWO_STAGE_FORMAT = "navsim-lb/submission-two-stage"
FORMAT_VERSION = 1
# NAVSIM v2's two-stage pickle (and our JSON of it): each a list of one token -> Trajectory dict per seed.
STAGE_FIELDS = ("first_stage_predictions", "second_stage_predictions")
NUM_POSES = 8
TIME_HORIZON_S = 4.0
INTERVAL_LENGTH_S = 0.5
# A submission holds at most MAX_SEEDS seeds; with the split's tokens this bounds the bytes a valid one can take
# (ContentLimit), which is where a decompression bomb is stopped. Per token and seed, 8 poses take at most
# POSES_BYTES_BOUND in any form the loader reads: about 660 bytes as compact JSON at full precision (a float64 is
# at most 24 characters), 1,440 as JSON indented by 4, 430 as a protocol-2 pickle of float64 (less in later
# protocols). The token itself comes on top: JSON may escape each character as a 12-byte surrogate pair. The
# metadata (8 fields of at most 1,000 characters, escaped), format and sampling fit in HEADER_BYTES_BOUND.
MAX_SEEDS = 32
POSES_BYTES_BOUND = 2048
TOKEN_CHAR_BYTES_BOUND = 12
HEADER_BYTES_BOUND = 1 << 20
MAX_ARRAY_ELEMENTS = 1 << 20
MAX_METADATA_CHARS = 1000
MAX_PROBLEMS = 50

# NAVSIM's pickle keys its metadata like this; the last one is literally "country / region".
PICKLE_METADATA_KEYS = {
    "team_name": "team_name",
    "authors": "authors",
    "email": "email",
    "institution": "institution",
    "country / region": "country",
}
# A team name written as the leaderboard rules ask: `<a href=URL>Method</a>` (compiled on first use: pickles only).
_HTML_LINK = r"""^\s*<a\s+href\s*=\s*["']?([^"'>\s]+)["']?[^>]*>(.*?)</a>\s*$"""


class Problem(NamedTuple):
    """One thing wrong with a submission; `token` and `field` say where (None when not about one)."""

    token: str | None
    field: str | None
    message: str

    def __str__(self) -> str:
        where = ", ".join(
            part for part in (self.field, f"token {self.token}" if self.token else None) if part
        )
        return f"{where}: {self.message}" if where else self.message


class SubmissionError(Exception):
    """A submission that cannot be read; `problems` lists every reason found.

    `seed_tokens` holds the tokens each seed named (readable or not) when the file got that far, so
    coverage of the split can still be reported alongside the other problems; for a two-stage submission
    they are the first stage's, and `second_stage_tokens` the second stage's.
    """

    def __init__(
        self,
        problems: Sequence[Problem],
        seed_tokens: Sequence[Sequence[str]] = (),
        second_stage_tokens: Sequence[Sequence[str]] = (),
    ) -> None:
        self.problems = list(problems)
        self.seed_tokens = [list(tokens) for tokens in seed_tokens]
        self.second_stage_tokens = [list(tokens) for tokens in second_stage_tokens]
        super().__init__("; ".join(str(problem) for problem in self.problems))


class SubmissionMetadata(NamedTuple):
    """Who submitted what; every field is optional text."""

    team_name: str = ""
    authors: str = ""
    email: str = ""
    institution: str = ""
    country: str = ""
    method: str = ""
    tech_report_url: str = ""
    code_url: str = ""


class Submission(NamedTuple):
    """Metadata and one token -> (8, 3) ego-frame poses mapping per seed."""

    metadata: SubmissionMetadata
    seeds: tuple[dict[str, FloatArray], ...]


class TwoStageSubmission(NamedTuple):
    """Metadata and, per seed, the stage-one and the stage-two token -> (8, 3) ego-frame poses mappings."""

    metadata: SubmissionMetadata
    first_stage: tuple[dict[str, FloatArray], ...]
    second_stage: tuple[dict[str, FloatArray], ...]


class ByteSource(Protocol):
    """Where a file's bytes are read from, as they arrive: `read(size)` returns at most `size` of them (all the
    rest for -1), b'' at the end."""

    def read(self, size: int = -1, /) -> bytes: ...


Seeds = tuple[tuple[dict[str, FloatArray], ...], list[list[str]]]  # readable poses, every token, per seed


class _Problems:
    """Collects problems, keeping the first MAX_PROBLEMS and counting the rest."""

    def __init__(self) -> None:
        self.items: list[Problem] = []
        self.dropped = 0

    def add(self, token: str | None, field: str | None, message: str) -> None:
        if len(self.items) < MAX_PROBLEMS:
            self.items.append(Problem(token, field, message))
        else:
            self.dropped += 1

    def result(self) -> list[Problem]:
        if self.dropped:
            return [*self.items, Problem(None, None, f"{self.dropped} more problem(s) not listed")]
        return list(self.items)

    def raise_if_any(self, seed_tokens: Sequence[Sequence[str]] = ()) -> None:
        if self.items:
            raise SubmissionError(self.result(), seed_tokens)


def _seed_field(seed: int, seed_count: int, field: str = "predictions") -> str:
    return f"{field}[{seed}]" if seed_count > 1 else field


def _kind_of_value(values: np.ndarray) -> str:
    """Name what stands where a number was expected, as a person says it (not numpy's dtype name)."""
    kind = {
        "U": "text",
        "S": "bytes",
        "b": "true/false",
        "c": "a complex number",
        "M": "a date",
        "m": "a duration",
    }
    if values.dtype.kind in kind:
        return kind[values.dtype.kind]
    found = {type(value).__name__ for value in values.ravel().tolist()} - {"int", "float"}
    names = {
        "str": "text",
        "NoneType": "null",
        "bool": "true/false",
        "list": "a nested list",
        "dict": "an object",
    }
    return " and ".join(sorted(names.get(name, name) for name in found)) or "something else"


def _check_poses(values: Any, token: str, field: str, problems: _Problems) -> FloatArray | None:
    """Return `values` as (8, 3) finite float64 poses, or record why they are not."""
    try:
        poses = np.asarray(values)
    except (ValueError, TypeError):
        problems.add(token, field, "poses must be a list of 8 [x, y, heading] numbers")
        return None
    if poses.dtype.kind not in "fiu":
        problems.add(
            token, field, f"poses must be numbers, found {_kind_of_value(poses)} where a number was expected"
        )
        return None
    if poses.shape != (NUM_POSES, 3):
        problems.add(token, field, f"expected {NUM_POSES} poses of [x, y, heading], got shape {poses.shape}")
        return None
    poses = poses.astype(np.float64, copy=False)  # read as float64 already: kept, not copied
    if not np.isfinite(poses).all():
        row, column = (int(i) for i in np.argwhere(~np.isfinite(poses))[0])
        problems.add(token, f"{field}[{row}][{column}]", "values must be finite (no NaN or infinity)")
        return None
    return poses


def _text(value: Any, field: str, problems: _Problems) -> str:
    if value is None:
        return ""
    if not isinstance(value, str):
        problems.add(None, field, f"must be text, got {type(value).__name__}")
        return ""
    if len(value) > MAX_METADATA_CHARS:
        problems.add(None, field, f"longer than {MAX_METADATA_CHARS} characters")
        return ""
    return value.strip()


def _check_sampling(
    num_poses: Any,
    time_horizon: Any,
    interval_length: Any,
    token: str | None,
    field: str,
    problems: _Problems,
) -> bool:
    # The leaderboard scores NAVSIM's default sampling only, as the official leaderboard does.
    expected = (NUM_POSES, TIME_HORIZON_S, INTERVAL_LENGTH_S)
    actual = (num_poses, time_horizon, interval_length)
    numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in actual)
    if not numbers or not all(
        math.isclose(a, e, abs_tol=1e-9) for a, e in zip(actual, expected, strict=True)
    ):
        problems.add(
            token,
            field,
            f"expected num_poses {NUM_POSES}, time_horizon {TIME_HORIZON_S}, interval_length "
            f"{INTERVAL_LENGTH_S}; got {num_poses!r}, {time_horizon!r}, {interval_length!r}",
        )
        return False
    return True


# JSON ---------------------------------------------------------------------------------------------


class _DuplicateKeys(dict[str, Any]):
    """A JSON object that remembers which keys were repeated (json keeps only the last value)."""

    duplicates: list[str]


def _object_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    result = _DuplicateKeys()
    result.duplicates = []
    for key, value in pairs:
        if key in result:
            result.duplicates.append(key)
        result[key] = value
    return result


JSON_HEADER_FIELDS = {
    "format",
    "version",
    "trajectory_sampling",
    *SubmissionMetadata._fields,
}


def _small_leaf(value: Any) -> Any:
    """Keep a token's poses as read from JSON small: as an array when numpy reads them as numbers (what
    `_check_poses` makes of them first, so it finds the same), else as they are (it names what is wrong)."""
    try:
        poses = np.asarray(value)
    except Exception:  # noqa: BLE001 - `_check_poses` meets the same value and says what is wrong with it
        return value
    return poses if poses.dtype.kind in "fiu" else value


def _json_document(content: ByteSource) -> dict[str, Any]:
    from scorer.json_stream import read_json

    try:
        # NaN and Infinity (which Python's json writes) are read, then reported per token as non-finite.
        document = read_json(
            content, {"predictions", *STAGE_FIELDS}, _small_leaf, _object_pairs, HEADER_BYTES_BOUND
        )
    except (UnicodeDecodeError, ValueError) as error:
        raise SubmissionError([Problem(None, None, f"not valid JSON: {error}")]) from None
    except RecursionError:
        raise SubmissionError(
            [Problem(None, None, "not a submission: arrays or objects nested too deeply")]
        ) from None
    if not isinstance(document, dict):
        raise SubmissionError([Problem(None, None, "the JSON document must be an object")])
    return document


def _json_header(
    document: dict[str, Any], format_name: str, prediction_fields: Sequence[str], problems: _Problems
) -> SubmissionMetadata:
    """Check the fields of a JSON submission other than its predictions; return its metadata."""
    if document.get("format") != format_name:
        hint = ""
        if {*STAGE_FIELDS, "predictions"} & set(document) - set(prediction_fields):
            hint = " (one-stage and two-stage submissions are scored under different metric versions)"
        problems.add(None, "format", f"must be {format_name!r}, got {document.get('format')!r}{hint}")
    if document.get("version") != FORMAT_VERSION:
        problems.add(None, "version", f"must be {FORMAT_VERSION}, got {document.get('version')!r}")
    for key in sorted(set(document) - JSON_HEADER_FIELDS - set(prediction_fields)):
        problems.add(None, key, "unknown field")
    metadata = SubmissionMetadata(
        **{name: _text(document.get(name), name, problems) for name in SubmissionMetadata._fields}
    )
    sampling = document.get(
        "trajectory_sampling", {"time_horizon": TIME_HORIZON_S, "interval_length": INTERVAL_LENGTH_S}
    )
    if isinstance(sampling, dict):
        horizon, interval = sampling.get("time_horizon"), sampling.get("interval_length")
        is_number = all(isinstance(v, int | float) for v in (horizon, interval))
        num_poses = sampling.get("num_poses", round(horizon / interval) if is_number and interval else None)
        _check_sampling(num_poses, horizon, interval, None, "trajectory_sampling", problems)
    else:
        problems.add(None, "trajectory_sampling", "must be an object with time_horizon and interval_length")
    return metadata


def _json_predictions(predictions: Any, problems: _Problems, field_name: str) -> Seeds:
    """Return the readable poses of each seed and every token each seed names."""
    if isinstance(predictions, dict):
        per_seed = [predictions]
    elif isinstance(predictions, list) and predictions:
        per_seed = predictions
    else:
        problems.add(
            None,
            field_name,
            "must be an object token -> poses, or a non-empty list of them (one per seed)",
        )
        return (), []
    seeds = []
    seed_tokens = []
    for seed, mapping in enumerate(per_seed):
        field = _seed_field(seed, len(per_seed), field_name)
        if not isinstance(mapping, dict):
            problems.add(None, field, f"must be an object token -> poses, got {type(mapping).__name__}")
            continue
        for token in getattr(mapping, "duplicates", []):
            problems.add(token, field, "token appears more than once")
        poses = {
            token: _check_poses(values, token, f"{field}[{token!r}]", problems)
            for token, values in mapping.items()
        }
        seeds.append({token: value for token, value in poses.items() if value is not None})
        seed_tokens.append(list(mapping))
    return tuple(seeds), seed_tokens


# NAVSIM pickle ------------------------------------------------------------------------------------


class _Record:
    """Inert stand-in for a pickled dataclass: NEWOBJ makes it empty, BUILD fills `state`."""

    def __init__(self) -> None:
        self.state: dict[str, Any] = {}

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, dict):
            raise pickle.UnpicklingError(f"{type(self).__name__} state must be a dict")
        self.state = state


class _Trajectory(_Record):
    pass


class _TrajectorySampling(_Record):
    pass


class _DType:
    """numpy.dtype(code, align, copy) restricted to float codes; BUILD gives the byte order."""

    ALLOWED = frozenset({"f2", "f4", "f8"})

    def __init__(self, code: Any, align: Any = False, copy: Any = True) -> None:
        if code not in self.ALLOWED:
            raise pickle.UnpicklingError(
                f"array dtype {code!r} is not allowed; poses must be float32 or float64"
            )
        self.dtype = np.dtype(code)

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) < 2 or state[1] not in ("<", ">", "=", "|"):
            raise pickle.UnpicklingError("malformed dtype state")
        self.dtype = self.dtype.newbyteorder(state[1])


class _NDArrayType:
    """Marks numpy.ndarray as the class argument of _reconstruct; never instantiated."""


def _array(raw: Any, dtype: Any, shape: Any, fortran: bool) -> FloatArray:
    if not isinstance(dtype, _DType):
        raise pickle.UnpicklingError("array dtype must come from numpy.dtype")
    if not (
        isinstance(shape, tuple) and all(isinstance(n, int) and n >= 0 for n in shape) and len(shape) <= 4
    ):
        raise pickle.UnpicklingError("malformed array shape")
    count = math.prod(shape)
    if count > MAX_ARRAY_ELEMENTS:
        raise pickle.UnpicklingError(f"array of {count} elements is too large")
    if not isinstance(raw, bytes | bytearray) or len(raw) != count * dtype.dtype.itemsize:
        raise pickle.UnpicklingError("array data does not match its shape and dtype")
    values = np.frombuffer(bytes(raw), dtype=dtype.dtype).reshape(shape, order="F" if fortran else "C")
    return values.astype(np.float64)


class _ArrayBuilder:
    """numpy's `_reconstruct(ndarray, (0,), b'b')` followed by BUILD (version, shape, dtype, fortran, raw)."""

    def __init__(self) -> None:
        self.array: FloatArray | None = None

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) != 5:
            raise pickle.UnpicklingError("malformed array state")
        _version, shape, dtype, fortran, raw = state
        self.array = _array(raw, dtype, shape, bool(fortran))


def _reconstruct(cls: Any, shape: Any, typecode: Any) -> _ArrayBuilder:
    if cls is not _NDArrayType:
        raise pickle.UnpicklingError("only numpy.ndarray may be reconstructed")
    return _ArrayBuilder()


def _frombuffer(buffer: Any, dtype: Any, shape: Any, order: Any) -> FloatArray:
    return _array(buffer, dtype, shape, order == "F")


def _latin1_encode(text: Any, encoding: Any = "latin1") -> bytes:
    # Protocol 2 writes bytes as latin-1 text through _codecs.encode.
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError("only latin-1 text may be encoded")
    return text.encode("latin1")


_ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    ("navsim.common.dataclasses", "Trajectory"): _Trajectory,
    ("nuplan.planning.simulation.trajectory.trajectory_sampling", "TrajectorySampling"): _TrajectorySampling,
    ("numpy", "ndarray"): _NDArrayType,
    ("numpy", "dtype"): _DType,
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy.core.numeric", "_frombuffer"): _frombuffer,
    ("numpy._core.numeric", "_frombuffer"): _frombuffer,
    ("_codecs", "encode"): _latin1_encode,
}


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"the pickle refers to {module}.{name}, which a NAVSIM submission never holds"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError("persistent ids are not allowed")


# What a damaged or hostile stream raises inside the unpickler: the file's fault, reported, never executed around.
UNPICKLING_ERRORS = (
    pickle.UnpicklingError,
    EOFError,
    ValueError,
    TypeError,
    AttributeError,
    IndexError,
    KeyError,
    OverflowError,
    RecursionError,
)


class _CheckedPickle:
    """The bytes of a pickle, handed to the unpickler only once their opcodes were walked (pickletools reads
    only the bytes that are there): a damaged stream can declare an argument longer than the file or a memo
    index far beyond its size, which the C unpickler would allocate memory for before failing. A pickler
    numbers its memo entries in sequence. Read as the unpickler asks: nothing past the opcode it needs."""

    def __init__(self, content: ByteSource) -> None:
        import pickletools  # only pickles need it: JSON submissions and the scoring path start without it

        self._content, self._ahead, self._walked = content, bytearray(), bytearray()
        self._opcodes = pickletools.genops(cast(IO[bytes], _Recorder(self)))
        self._memo_size = 0

    def _fetch(self) -> bool:
        data = self._content.read(_INPUT_BYTES)
        self._ahead += data
        return bool(data)

    def _step(self) -> bool:
        """Walk one opcode (with its argument); return False once the pickle has ended."""
        step = next(self._opcodes, None)
        if step is None:
            return False
        opcode, argument, _ = step
        if opcode.name == "MEMOIZE":
            self._memo_size += 1
        elif opcode.name in ("PUT", "BINPUT", "LONG_BINPUT"):
            index = cast(int, argument)  # these opcodes carry an integer
            if index > self._memo_size:
                # Not an UnpicklingError, which the C unpickler reports as "Ran out of input".
                raise ValueError(f"memo index {index} out of sequence")
            self._memo_size = max(self._memo_size, index + 1)
        return True

    def _give(self, size: int) -> bytes:
        data = bytes(self._walked[:size])
        del self._walked[:size]
        return data

    def read(self, size: int = -1) -> bytes:
        while (size < 0 or len(self._walked) < size) and self._step():
            pass
        return self._give(len(self._walked) if size < 0 else size)

    def readinto(self, buffer: Any) -> int:
        data = self.read(len(buffer))
        buffer[: len(data)] = data
        return len(data)

    def readline(self) -> bytes:
        while b"\n" not in self._walked and self._step():
            pass
        return self._give(self._walked.find(b"\n") + 1 or len(self._walked))


class _Recorder:
    """What pickletools reads of a _CheckedPickle's content: each byte read is kept for the unpickler."""

    def __init__(self, pickle_: _CheckedPickle) -> None:
        self._of = pickle_

    def _take(self, size: int) -> bytes:
        of = self._of
        data = bytes(of._ahead[:size])
        del of._ahead[:size]
        of._walked += data
        return data

    def read(self, size: int) -> bytes:
        ahead = self._of._ahead
        while len(ahead) < size and len(ahead) <= HEADER_BYTES_BOUND and self._of._fetch():
            pass
        if len(ahead) < size and len(ahead) > HEADER_BYTES_BOUND:
            # A NAVSIM submission's largest argument is a token, a metadata text or an array's bytes.
            raise ValueError(f"an argument of {size:,} bytes, more than a NAVSIM submission's pickle holds")
        return self._take(size)

    def readline(self) -> bytes:
        while b"\n" not in self._of._ahead and self._of._fetch():
            pass
        end = self._of._ahead.find(b"\n") + 1 or len(self._of._ahead)
        return self._take(end)


def _unpickle(content: ByteSource) -> Any:
    try:
        return _RestrictedUnpickler(_CheckedPickle(content)).load()
    # With sizes bounded by `_CheckedPickle`, the C unpickler still reports some damaged frames as MemoryError.
    except (*UNPICKLING_ERRORS, MemoryError) as error:
        # Any failure inside the stream is the file's fault: report it, never execute around it.
        raise SubmissionError(
            [Problem(None, None, f"not a readable NAVSIM submission pickle: {error}")]
        ) from None


def _pickle_trajectory(value: Any, token: Any, field: str, problems: _Problems) -> FloatArray | None:
    if not isinstance(token, str):
        problems.add(None, field, f"tokens must be text, got {type(token).__name__}")
        return None
    if not isinstance(value, _Trajectory):
        problems.add(token, field, f"must be a navsim Trajectory, got {type(value).__name__}")
        return None
    poses = value.state.get("poses")
    sampling = value.state.get("trajectory_sampling")
    if isinstance(poses, _ArrayBuilder):
        poses = poses.array
    if not isinstance(poses, np.ndarray):
        problems.add(token, f"{field}.poses", "must be a numpy float array")
        return None
    if not isinstance(sampling, _TrajectorySampling):
        problems.add(token, f"{field}.trajectory_sampling", "must be a TrajectorySampling")
        return None
    state = sampling.state
    sampling_field = f"{field}.trajectory_sampling"
    values = (state.get("num_poses"), state.get("time_horizon"), state.get("interval_length"))
    if not _check_sampling(*values, token, sampling_field, problems):
        return None
    return _check_poses(poses, token, f"{field}.poses", problems)


def _pickle_document(content: ByteSource) -> dict[Any, Any]:
    document = _unpickle(content)
    if not isinstance(document, dict):
        raise SubmissionError(
            [Problem(None, None, f"the pickle must hold a dict, got {type(document).__name__}")]
        )
    return document


def _pickle_metadata(
    document: dict[Any, Any], format_name: str, prediction_keys: Sequence[str], problems: _Problems
) -> SubmissionMetadata:
    """Check the keys of a NAVSIM pickle other than its predictions; return its metadata. The pickle names no
    format: its prediction keys tell a one-stage (`format_name` FORMAT) from a two-stage one."""
    if format_name == FORMAT and any(key in document for key in STAGE_FIELDS):
        problems.add(
            None,
            STAGE_FIELDS[0],
            "a two-stage (NAVSIM v2 pseudo-simulation) submission: score it under a two-stage version",
        )
        return SubmissionMetadata()
    for key in sorted(set(map(str, document)) - {*PICKLE_METADATA_KEYS, *prediction_keys}):
        problems.add(None, key, "unknown key")
    values = {name: _text(document.get(key), key, problems) for key, name in PICKLE_METADATA_KEYS.items()}
    # The leaderboard rules ask for team_name as `<a href=URL>Method</a>`: split it into method and link.
    link = re.match(_HTML_LINK, values["team_name"], re.IGNORECASE | re.DOTALL)
    if link:
        values["tech_report_url"], values["method"] = (
            link.group(1),
            re.sub(r"<[^>]*>", "", link.group(2)).strip(),
        )
    return SubmissionMetadata(**values)


def _pickle_predictions(predictions: Any, problems: _Problems, field_name: str) -> Seeds:
    """Return the readable poses of each seed and every token each seed names."""
    # v1.0 pickles hold one dict; v1.1 and v2 a list of dicts, one per seed.
    per_seed = [predictions] if isinstance(predictions, dict) else predictions
    if not isinstance(per_seed, list) or not per_seed:
        problems.add(None, field_name, "must be a dict token -> Trajectory or a non-empty list of them")
        return (), []
    seeds = []
    seed_tokens = []
    for seed, mapping in enumerate(per_seed):
        field = _seed_field(seed, len(per_seed), field_name)
        if not isinstance(mapping, dict):
            problems.add(None, field, f"must be a dict token -> Trajectory, got {type(mapping).__name__}")
            continue
        poses = {
            token: _pickle_trajectory(value, token, f"{field}[{token!r}]", problems)
            for token, value in mapping.items()
        }
        seeds.append({token: value for token, value in poses.items() if value is not None})
        seed_tokens.append([token for token in mapping if isinstance(token, str)])
    return tuple(seeds), seed_tokens


# Either form ----------------------------------------------------------------------------------------


class _Form(NamedTuple):
    """How one file form (JSON or pickle) gives its document, its metadata and one predictions field."""

    document: Callable[[ByteSource], dict[Any, Any]]
    metadata: Callable[[dict[Any, Any], str, Sequence[str], _Problems], SubmissionMetadata]
    predictions: Callable[[Any, _Problems, str], Seeds]


_JSON = _Form(_json_document, _json_header, _json_predictions)
_PICKLE = _Form(_pickle_document, _pickle_metadata, _pickle_predictions)


class SubmissionFile(NamedTuple):
    """A submission file's document, read in its form (JSON or pickle), before its fields are checked."""

    document: dict[Any, Any]
    form: _Form


def one_stage(read: SubmissionFile) -> Submission:
    """Return the one-stage submission a file's document holds; raises SubmissionError listing every problem."""
    document, form = read
    problems = _Problems()
    metadata = form.metadata(document, FORMAT, ["predictions"], problems)
    seeds, seed_tokens = form.predictions(document.get("predictions"), problems, "predictions")
    problems.raise_if_any(seed_tokens)
    return Submission(metadata, seeds)


def two_stage(read: SubmissionFile) -> TwoStageSubmission:
    """Return the two stages' seeds a file's document holds as one submission: seed i is the i-th dict of each
    stage's list. Raises SubmissionError listing every problem."""
    document, form = read
    problems = _Problems()
    metadata = form.metadata(document, TWO_STAGE_FORMAT, STAGE_FIELDS, problems)
    (first, first_tokens), (second, second_tokens) = (
        form.predictions(document.get(field), problems, field) for field in STAGE_FIELDS
    )
    if first_tokens and second_tokens and len(first_tokens) != len(second_tokens):
        problems.add(
            None,
            STAGE_FIELDS[1],
            f"{len(second_tokens)} seed(s), but {STAGE_FIELDS[0]} has {len(first_tokens)}: "
            "each seed is one dict in each list",
        )
    if problems.items:
        raise SubmissionError(problems.result(), first_tokens, second_tokens)
    return TwoStageSubmission(metadata, first, second)


# Entry points -------------------------------------------------------------------------------------


class ContentLimit(NamedTuple):
    """The most bytes a submission's content (decompressed) may take, and why that many."""

    bytes: int
    reason: str

    @classmethod
    def for_tokens(cls, tokens: Iterable[str], seeds: int = MAX_SEEDS) -> "ContentLimit":
        """The most a valid submission of `tokens` (every token a seed holds; a two-stage one's of both stages)
        with up to `seeds` seeds can take, in JSON or in pickle form."""
        tokens = list(tokens)
        per_seed = sum(POSES_BYTES_BOUND + TOKEN_CHAR_BYTES_BOUND * len(token) for token in tokens)
        return cls(
            HEADER_BYTES_BOUND + seeds * per_seed,
            f"the most a submission of this split can take: {len(tokens)} tokens x at most {seeds} seeds x "
            f"{NUM_POSES} poses, at most {POSES_BYTES_BOUND:,} bytes per token and seed as JSON or pickle, "
            f"and {HEADER_BYTES_BOUND / 2**20:.0f} MiB for the rest",
        )


# For a file read without its split (the engine's own commands, a stored file read again).
UNSPLIT_LIMIT = ContentLimit(1 << 30, "the most the loader reads of a file without knowing its split")
# The kinds of file the loader reads: a JSON document or a pickle, either optionally compressed once.
_COMPRESSED = {b"\x1f\x8b": "gzip", b"\xfd7zXZ\x00": "xz"}
# Kinds it names to say what a file is instead, by their first bytes.
_OTHER_KINDS = {
    b"PK\x03\x04": "a zip archive",
    b"PK\x05\x06": "a zip archive",
    b"BZh": "bzip2",
    b"\x28\xb5\x2f\xfd": "zstd",
    b"7z\xbc\xaf\x27\x1c": "a 7z archive",
    b"\x93NUMPY": "a numpy array (.npy)",
}
_JSON_BLANK = b" \t\r\n"
_NON_BLANK = re.compile(rb"[^ \t\r\n]")
# JSON in UTF-16 or UTF-32 starts with a byte-order mark; the json module reads it.
_WIDE_BOMS = (b"\xff\xfe", b"\xfe\xff", b"\x00\x00\xfe\xff")
_HEAD_BYTES = 64  # enough of a file's start to name its kind
_INPUT_BYTES = 1 << 16  # compressed bytes fed to a decompressor at a time
_OUTPUT_BYTES = 1 << 20  # and the most it gives back at a time
_READS = "the server reads navsim-lb JSON or a NAVSIM submission pickle, either one optionally gzip- or xz-compressed"


def _is_pickle(head: bytes) -> bool:
    return head[:1] == b"\x80"  # pickle protocol 2 and later start with the PROTO opcode


def _is_json(head: bytes) -> bool:
    if head.startswith(_WIDE_BOMS):
        return True
    return head.removeprefix(b"\xef\xbb\xbf").lstrip(_JSON_BLANK)[:1] in (b"{", b"[")


def file_kind(head: bytes) -> str:
    """Name what a file is from its first bytes: gzip, xz, zip, ..., a pickle of protocol N, JSON, text."""
    for magic, kind in (*_COMPRESSED.items(), *_OTHER_KINDS.items()):
        if head.startswith(magic):
            return kind
    if _is_pickle(head):
        return f"a pickle (protocol {head[1]})" if len(head) > 1 else "a pickle"
    if _is_json(head):
        return "JSON"
    start = head[:_HEAD_BYTES]
    text = start.decode("utf-8", errors="replace")
    if "\ufffd" not in text and all(c.isprintable() or c in "\t\r\n" for c in text):
        return f"text starting {text[:24]!r}"
    return f"data starting with the bytes {start[:8].hex(' ')}"


def _not_a_submission(filename: str, kind: str) -> SubmissionError:
    return SubmissionError([Problem(None, None, f"{filename} is {kind}, not a submission: {_READS}")])


def _too_large(filename: str, verb: str, limit: ContentLimit) -> SubmissionError:
    size = f"{limit.bytes:,} bytes ({limit.bytes / 2**20:.1f} MiB)"
    message = f"{filename} {verb} more than {size}, {limit.reason}; it was refused at that size"
    return SubmissionError([Problem(None, None, message)])


def _gunzip(pieces: Iterable[bytes]) -> Iterator[bytes]:
    """Yield what a gzip stream inflates to, at most _OUTPUT_BYTES at a time."""
    decompressor = zlib.decompressobj(wbits=31)
    for piece in pieces:
        pending: bytes = piece
        while not decompressor.eof:
            inflated = decompressor.decompress(pending, _OUTPUT_BYTES)
            pending = decompressor.unconsumed_tail
            yield inflated
            # A full output may leave more behind even when every input byte was taken.
            if not pending and len(inflated) < _OUTPUT_BYTES:
                break
        if decompressor.eof:
            return
    raise zlib.error("the stream ends early: the file was cut short")


def _unxz(pieces: Iterable[bytes]) -> Iterator[bytes]:
    """Yield what an xz stream inflates to, at most _OUTPUT_BYTES at a time."""
    decompressor = lzma.LZMADecompressor()
    for piece in pieces:
        pending = piece
        while not decompressor.eof:
            yield decompressor.decompress(pending, _OUTPUT_BYTES)
            pending = b""
            if decompressor.needs_input:
                break
        if decompressor.eof:
            return
    raise lzma.LZMAError("the stream ends early: the file was cut short")


_INFLATERS: dict[str, Callable[[Iterable[bytes]], Iterator[bytes]]] = {"gzip": _gunzip, "xz": _unxz}


def _pieces(start: bytes, source: ByteSource) -> Iterator[bytes]:
    """Yield `start`, then what `source` reads, _INPUT_BYTES at a time."""
    yield start
    while piece := source.read(_INPUT_BYTES):
        yield piece


class _Content:
    """A submission file's content (inflated when it is gzip or xz), read as the file streams in: refused
    once it passes what a valid submission of the split can take (`limit`), or, from its first bytes, when it
    holds neither JSON nor a pickle (compressed again, say). Holds at most one inflated piece at a time."""

    def __init__(self, source: ByteSource, filename: str, limit: ContentLimit) -> None:
        start = b""
        while len(start) < _HEAD_BYTES and (piece := source.read(_HEAD_BYTES - len(start))):
            start += piece
        if not start:
            raise SubmissionError([Problem(None, None, f"{filename} is empty")])
        self.compression = next(
            (kind for magic, kind in _COMPRESSED.items() if start.startswith(magic)), None
        )
        pieces = _pieces(start, source)
        self._pieces = pieces if self.compression is None else _INFLATERS[self.compression](pieces)
        self._filename, self._limit, self._size, self._buffer = filename, limit, 0, b""
        self.is_pickle = self._check_kind()

    def _next(self) -> bytes:
        """Return the next piece of content (b'' at its end)."""
        try:
            piece = next(self._pieces, b"")
        except (lzma.LZMAError, zlib.error) as error:
            raise SubmissionError(
                [Problem(None, None, f"corrupt {self.compression} file: {error}")]
            ) from None
        self._size += len(piece)
        if self._size > self._limit.bytes:
            verb = "is" if self.compression is None else f"({self.compression}) decompresses to"
            raise _too_large(self._filename, verb, self._limit)
        return piece

    def _check_kind(self) -> bool:
        """Refuse content that is neither JSON nor a pickle; return whether it is a pickle. Blank content is
        looked past (JSON may follow), and not held: a bomb of blanks costs one piece."""
        head, blank_start = b"", False
        while True:
            first = _NON_BLANK.search(head)
            if first is not None and len(head) - first.start() >= _HEAD_BYTES:
                break
            piece = self._next()
            if not piece:
                break
            if first is None and head:  # all blank so far: only what follows tells the kind
                blank_start, head = True, b""
            head += piece
        self._buffer = head
        _check_content_kind(head, self._filename, self.compression)
        return not blank_start and _is_pickle(head)

    def read(self, size: int = -1) -> bytes:
        """Return at most `size` bytes of content (all that is left for -1); b'' at its end."""
        if size < 0:
            rest = [self._buffer, *iter(self._next, b"")]
            self._buffer = b""
            return b"".join(rest)
        if not self._buffer:
            self._buffer = self._next()
        data, self._buffer = self._buffer[:size], self._buffer[size:]
        return data

    def drain(self) -> None:
        """Read the rest (a pickle ends at its STOP): a file is accepted only whole and within its limit."""
        self._buffer = b""
        while self._next():
            pass


def _check_content_kind(content: bytes, filename: str, compression: str | None) -> None:
    """Refuse content that is neither JSON nor a pickle, naming what it is (and in what compression)."""
    first = _NON_BLANK.search(content)
    if first is None:  # blank so far: JSON may follow
        return
    head = content[first.start() : first.start() + _HEAD_BYTES]
    if _is_pickle(head) or _is_json(head):
        return
    kind = file_kind(head)
    if compression is None:
        raise _not_a_submission(filename, kind)
    again = " (compress the file once)" if kind in _COMPRESSED.values() else ""
    raise _not_a_submission(filename, f"{compression} holding {kind}{again}")


def read_submission_file(
    source: ByteSource, filename: str = "submission", limit: ContentLimit = UNSPLIT_LIMIT
) -> SubmissionFile:
    """Read a submission file (JSON or NAVSIM pickle, optionally xz- or gzip-compressed) as it streams from
    `source`, to its document: one pass, holding one piece of the file and the document (the poses as arrays)
    in memory. Read `one_stage` or `two_stage` from it. Raises SubmissionError; `filename` only labels
    messages. Content past `limit` (decompressed) is refused as it inflates."""
    content = _Content(source, filename, limit)
    form = _PICKLE if content.is_pickle else _JSON
    try:
        document = form.document(content)
    except SubmissionError:
        content.drain()  # a file past its limit (a bomb) is refused as such, whatever its first bytes hold
        raise
    content.drain()
    return SubmissionFile(document, form)


def load_submission(
    data: bytes, filename: str = "submission", limit: ContentLimit = UNSPLIT_LIMIT
) -> Submission:
    """Read a submission (JSON or NAVSIM pickle, optionally xz- or gzip-compressed) from its bytes.

    Raises SubmissionError listing every problem; `filename` only labels messages. Content past `limit`
    (decompressed) is refused as it inflates.
    """
    return one_stage(read_submission_file(io.BytesIO(data), filename, limit))


def load_two_stage_submission(
    data: bytes, filename: str = "submission", limit: ContentLimit = UNSPLIT_LIMIT
) -> TwoStageSubmission:
    """Read a two-stage submission (`navsim-lb/submission-two-stage` JSON or NAVSIM v2's pickle with
    `first_stage_predictions` and `second_stage_predictions`, optionally xz- or gzip-compressed).

    Several seeds are allowed (the official script refuses them): seed i is the i-th dict of both lists.
    Raises SubmissionError listing every problem; content past `limit` (decompressed) is refused as it inflates.
    """
    return two_stage(read_submission_file(io.BytesIO(data), filename, limit))


def coverage_problems(
    seed_tokens: Sequence[Iterable[str]], tokens: Iterable[str], field_name: str = "predictions"
) -> list[Problem]:
    """Return what keeps each seed's tokens from covering the split `tokens` exactly."""
    problems = _Problems()
    _add_coverage(seed_tokens, tokens, field_name, problems)
    return problems.result()


def _add_coverage(
    seed_tokens: Sequence[Iterable[str]], tokens: Iterable[str], field_name: str, problems: _Problems
) -> None:
    expected = list(tokens)
    expected_set = set(expected)
    for seed, named in enumerate(seed_tokens):
        present = set(named)
        field = _seed_field(seed, len(seed_tokens), field_name)
        for token in (t for t in expected if t not in present):
            problems.add(token, field, "token of the split is missing")
        for token in (t for t in named if t not in expected_set):
            problems.add(token, field, "token is not in the split")


def two_stage_coverage_problems(
    first_stage: Sequence[Iterable[str]],
    second_stage: Sequence[Iterable[str]],
    stage_one_tokens: Iterable[str],
    stage_two_tokens: Iterable[str],
) -> list[Problem]:
    """Return what keeps each seed of each stage from covering its stage's tokens exactly: every missing and
    every extra token, the field naming the stage (`first_stage_predictions` or `second_stage_predictions`)."""
    problems = _Problems()
    _add_coverage(first_stage, stage_one_tokens, STAGE_FIELDS[0], problems)
    _add_coverage(second_stage, stage_two_tokens, STAGE_FIELDS[1], problems)
    return problems.result()


def validate_submission(submission: Submission, tokens: Iterable[str]) -> list[Problem]:
    """Return what keeps `submission` from covering the split `tokens` exactly once per seed, with at most
    MAX_SEEDS seeds."""
    problems = coverage_problems([list(seed) for seed in submission.seeds], tokens)
    if len(submission.seeds) > MAX_SEEDS:
        message = f"{len(submission.seeds)} seeds: a submission holds at most {MAX_SEEDS}"
        problems.insert(0, Problem(None, "predictions", message))
    return problems


def _seeds_json(seeds: Sequence[Mapping[str, FloatArray]]) -> Any:
    """Return seeds as a JSON predictions field: one dict for a single seed, else a list of them."""
    predictions = [{token: poses.tolist() for token, poses in seed.items()} for seed in seeds]
    return predictions[0] if len(predictions) == 1 else predictions


def _dump_json(metadata: SubmissionMetadata, format_name: str, fields_: dict[str, Any]) -> bytes:
    document = {
        "format": format_name,
        "version": FORMAT_VERSION,
        **metadata._asdict(),
        "trajectory_sampling": {"time_horizon": TIME_HORIZON_S, "interval_length": INTERVAL_LENGTH_S},
        **fields_,
    }
    return json.dumps(document).encode()


def dump_submission_json(submission: Submission) -> bytes:
    """Return `submission` as `navsim-lb/submission` JSON (exact float round trip)."""
    return _dump_json(submission.metadata, FORMAT, {"predictions": _seeds_json(submission.seeds)})


def dump_two_stage_submission_json(submission: TwoStageSubmission) -> bytes:
    """Return `submission` as `navsim-lb/submission-two-stage` JSON (exact float round trip)."""
    stages = (submission.first_stage, submission.second_stage)
    return _dump_json(
        submission.metadata,
        TWO_STAGE_FORMAT,
        {field: _seeds_json(seeds) for field, seeds in zip(STAGE_FIELDS, stages, strict=True)},
    )
