"""Submission loading: JSON and NAVSIM pickles (every protocol, compressed or not), and every refusal."""

from __future__ import annotations

import bz2
import gzip
import io
import json
import lzma
import pickle
import sys
import tracemalloc
import types
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from hostile import JSON_START, gzip_bomb
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scorer.submission import (
    HEADER_BYTES_BOUND,
    MAX_SEEDS,
    UNSPLIT_LIMIT,
    ContentLimit,
    Submission,
    SubmissionError,
    SubmissionMetadata,
    coverage_problems,
    dump_submission_json,
    file_kind,
    load_submission,
    validate_submission,
)

TOKENS = ["a1", "b2", "c3"]


def _poses(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(8, 3))


def _document(**changes: object) -> dict[str, object]:
    document: dict[str, object] = {
        "format": "navsim-lb/submission",
        "version": 1,
        "team_name": "team",
        "method": "method",
        "trajectory_sampling": {"time_horizon": 4.0, "interval_length": 0.5},
        "predictions": {token: _poses(i).tolist() for i, token in enumerate(TOKENS)},
    }
    document.update(changes)
    return document


def _problems(data: bytes) -> list[tuple[str | None, str | None, str]]:
    with pytest.raises(SubmissionError) as error:
        load_submission(data, "upload.json")
    return [(p.token, p.field, p.message) for p in error.value.problems]


def test_json_round_trip_is_exact() -> None:
    submission = load_submission(json.dumps(_document()).encode())
    assert submission.metadata.method == "method"
    assert list(submission.seeds[0]) == TOKENS
    np.testing.assert_array_equal(submission.seeds[0]["b2"], _poses(1))
    again = load_submission(dump_submission_json(submission))
    assert list(again.seeds[0]) == TOKENS
    assert all(np.array_equal(again.seeds[0][t], submission.seeds[0][t]) for t in TOKENS)
    assert again.metadata == submission.metadata


def test_json_multi_seed() -> None:
    seeds = [{t: _poses(i + 10 * s).tolist() for i, t in enumerate(TOKENS)} for s in range(3)]
    submission = load_submission(json.dumps(_document(predictions=seeds)).encode())
    assert len(submission.seeds) == 3
    np.testing.assert_array_equal(submission.seeds[2]["a1"], _poses(20))
    assert len(load_submission(dump_submission_json(submission)).seeds) == 3


def test_json_problems_name_token_and_field() -> None:
    predictions = {
        "a1": _poses(0).tolist()[:7],
        "b2": [[1.0, 2.0, "x"]] * 8,
        "c3": _poses(2).tolist(),
    }
    found = _problems(json.dumps(_document(predictions=predictions, format="other", extra=1)).encode())
    assert (None, "format", "must be 'navsim-lb/submission', got 'other'") in found
    assert (None, "extra", "unknown field") in found
    assert ("a1", "predictions['a1']", "expected 8 poses of [x, y, heading], got shape (7, 3)") in found
    assert any(token == "b2" and "numbers" in message for token, _, message in found)


def test_json_non_finite_values_and_duplicates_are_refused() -> None:
    document = _document()
    document["predictions"]["b2"][0][0] = float("nan")  # type: ignore[index]
    text = json.dumps(document)
    assert _problems(text.encode()) == [
        ("b2", "predictions['b2'][0][0]", "values must be finite (no NaN or infinity)")
    ]
    row = "[[1e400, 0.0, 0.0]" + ", [0.0, 0.0, 0.0]" * 7 + "]"
    text = json.dumps(_document(predictions={})).replace(
        '"predictions": {}', f'"predictions": {{"a1": {row}}}'
    )
    assert _problems(text.encode()) == [
        ("a1", "predictions['a1'][0][0]", "values must be finite (no NaN or infinity)")
    ]
    first, second = json.dumps(_poses(0).tolist()), json.dumps(_poses(1).tolist())
    text = f'{{"format": "navsim-lb/submission", "version": 1, "predictions": {{"a1": {first}, "a1": {second}}}}}'
    assert _problems(text.encode()) == [("a1", "predictions", "token appears more than once")]


def test_wrong_sampling_is_refused() -> None:
    document = _document(trajectory_sampling={"time_horizon": 4.0, "interval_length": 0.1})
    ((token, field, message),) = _problems(json.dumps(document).encode())
    assert token is None and field == "trajectory_sampling" and "interval_length 0.5" in message


def test_garbage_is_refused_with_a_message() -> None:
    for data in (b"", b"not json", b"[1, 2]", lzma.compress(b"{")[:-5], b"\x80\x04garbage"):
        with pytest.raises(SubmissionError) as error:
            load_submission(data, "x")
        assert error.value.problems and error.value.problems[0].message


def test_problem_list_is_capped() -> None:
    predictions = {f"t{i}": [[0.0]] for i in range(200)}
    found = _problems(json.dumps(_document(predictions=predictions)).encode())
    assert len(found) == 51 and found[-1] == (None, None, "150 more problem(s) not listed")


def test_validate_against_split() -> None:
    submission = load_submission(json.dumps(_document()).encode())
    assert validate_submission(submission, TOKENS) == []
    problems = validate_submission(submission, ["a1", "b2", "zz"])
    assert [(p.token, p.message) for p in problems] == [
        ("zz", "token of the split is missing"),
        ("c3", "token is not in the split"),
    ]


# NAVSIM pickles: stand-in classes registered under the devkit's module paths ---------------------


@dataclass
class TrajectorySampling:
    num_poses: int = 8
    time_horizon: float = 4.0
    interval_length: float = 0.5


@dataclass
class Trajectory:
    poses: np.ndarray
    trajectory_sampling: TrajectorySampling


@pytest.fixture
def devkit_classes() -> Iterator[None]:
    """Make pickle write the devkit's module paths for the stand-in classes."""
    modules = {
        "navsim.common.dataclasses": Trajectory,
        "nuplan.planning.simulation.trajectory.trajectory_sampling": TrajectorySampling,
    }
    packages = {".".join(name.split(".")[:i]) for name in modules for i in range(1, name.count(".") + 2)}
    saved = {name: sys.modules.get(name) for name in packages}
    for name in packages:
        sys.modules[name] = types.ModuleType(name)
    for name, cls in modules.items():
        setattr(sys.modules[name], cls.__name__, cls)
        cls.__module__ = name
        cls.__qualname__ = cls.__name__
    yield
    for name, module in saved.items():
        if module is None:
            sys.modules.pop(name, None)
        else:
            sys.modules[name] = module


def _navsim_pickle(predictions: object, protocol: int, **metadata: object) -> bytes:
    document = {
        "team_name": "<a href=https://example.org/paper>Great Planner</a>",
        "authors": "A. Author",
        "email": "a@example.org",
        "institution": "Uni",
        "country / region": "Nowhere",
        "predictions": predictions,
    }
    document.update(metadata)
    return pickle.dumps(document, protocol=protocol)


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_navsim_pickle_every_protocol(devkit_classes: None, protocol: int, dtype: type) -> None:
    sampling = TrajectorySampling()
    seeds = [
        {t: Trajectory(_poses(i + s).astype(dtype), sampling) for i, t in enumerate(TOKENS)} for s in range(2)
    ]
    submission = load_submission(_navsim_pickle(seeds, protocol), "submission.pkl")
    assert len(submission.seeds) == 2
    np.testing.assert_array_equal(submission.seeds[1]["c3"], _poses(3).astype(dtype).astype(np.float64))
    assert submission.metadata.method == "Great Planner"
    assert submission.metadata.tech_report_url == "https://example.org/paper"
    assert submission.metadata.country == "Nowhere"


def test_navsim_v10_pickle_xz_and_fortran_arrays(devkit_classes: None) -> None:
    sampling = TrajectorySampling()
    predictions = {t: Trajectory(np.asfortranarray(_poses(i)), sampling) for i, t in enumerate(TOKENS)}
    data = lzma.compress(_navsim_pickle(predictions, 4), preset=0)
    submission = load_submission(data, "submission.pkl")
    np.testing.assert_array_equal(submission.seeds[0]["a1"], _poses(0))


def test_navsim_pickle_problems(devkit_classes: None) -> None:
    sampling = TrajectorySampling()
    predictions = {
        "a1": Trajectory(np.zeros((6, 3)), sampling),
        "b2": Trajectory(np.zeros((8, 3)), TrajectorySampling(num_poses=40, interval_length=0.1)),
        "c3": Trajectory(np.full((8, 3), np.inf), sampling),
    }
    with pytest.raises(SubmissionError) as error:
        load_submission(_navsim_pickle(predictions, 4, team_name=["not", "text"]), "s.pkl")
    found = {(p.token, p.field) for p in error.value.problems}
    assert {
        (None, "team_name"),
        ("a1", "predictions['a1'].poses"),
        ("b2", "predictions['b2'].trajectory_sampling"),
        ("c3", "predictions['c3'].poses[0][0]"),
    } == found


class Exploit:
    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (print, ("executed",))


def test_pickle_with_foreign_globals_is_refused_without_running_them(
    capsys: pytest.CaptureFixture[str],
) -> None:
    for payload in (pickle.dumps({"predictions": Exploit()}), pickle.dumps({"predictions": {"a": object}})):
        with pytest.raises(SubmissionError) as error:
            load_submission(payload, "evil.pkl")
        assert "which a NAVSIM submission never holds" in str(error.value)
    assert "executed" not in capsys.readouterr().out


def test_pickle_object_arrays_are_refused(devkit_classes: None) -> None:
    poses = np.empty((8, 3), dtype=object)
    poses[:] = 0.0
    data = _navsim_pickle({"a1": Trajectory(poses, TrajectorySampling())}, 4)
    with pytest.raises(SubmissionError) as error:
        load_submission(data, "s.pkl")
    assert "never holds" in str(error.value) or "dtype" in str(error.value)


def test_dump_keeps_metadata() -> None:
    metadata = SubmissionMetadata(team_name="t", method="m", code_url="https://example.org/code")
    submission = Submission(metadata, ({"a1": _poses(0)},))
    assert load_submission(dump_submission_json(submission)).metadata == metadata


def test_unreadable_file_still_reports_split_coverage() -> None:
    document = _document(predictions={"a1": [[0.0]], "zz": _poses(0).tolist()})
    with pytest.raises(SubmissionError) as error:
        load_submission(json.dumps(document).encode())
    assert error.value.seed_tokens == [["a1", "zz"]]
    problems = coverage_problems(error.value.seed_tokens, TOKENS)
    assert [(p.token, p.message) for p in problems] == [
        ("b2", "token of the split is missing"),
        ("c3", "token of the split is missing"),
        ("zz", "token is not in the split"),
    ]


# Damaged files: whatever the bytes, the loader refuses them with problems, never with another exception, or
# loads a well-formed file (a changed digit or letter can leave one) with nothing dropped or invented.


def _damaged(data: bytes, edits: list[tuple[int, int, int]]) -> bytes:
    """Apply (kind, position, byte) edits: 0 replaces, 1 inserts, 2 deletes the byte at position."""
    damaged = bytearray(data)
    for kind, position, value in edits:
        at = position % (len(damaged) + 1)
        if kind == 0 and at < len(damaged):
            damaged[at] = value
        elif kind == 1:
            damaged.insert(at, value)
        elif at < len(damaged):
            del damaged[at]
    return bytes(damaged)


EDITS = st.lists(
    st.tuples(st.integers(0, 2), st.integers(0, 10_000), st.integers(0, 255)), min_size=1, max_size=6
)


def _assert_problems(error: SubmissionError) -> None:
    assert error.problems and all(problem.message.strip() for problem in error.problems)


def _loaded_or_refused(data: bytes, name: str) -> Submission | None:
    """The submission `data` holds, or None when it is refused with problems, each with a message."""
    try:
        return load_submission(data, name)
    except SubmissionError as error:
        _assert_problems(error)
        return None


def _json_as_read(data: bytes) -> Submission:
    """What the standard library reads from a JSON file. All but the metadata and the poses must be as written
    (format, version, sampling): the loader refuses a change to any of them."""
    document = json.loads(data)
    text = {name: (document.pop(name, None) or "").strip() for name in SubmissionMetadata._fields}
    predictions = document.pop("predictions")
    written = _document()
    assert document == {key: written[key] for key in ("format", "version", "trajectory_sampling")}
    per_seed = predictions if isinstance(predictions, list) else [predictions]
    seeds = tuple(
        {token: np.asarray(poses, dtype=np.float64) for token, poses in seed.items()} for seed in per_seed
    )
    return Submission(SubmissionMetadata(**text), seeds)


def _poses_lists(submission: Submission) -> list[dict[str, list[list[float]]]]:
    return [{token: poses.tolist() for token, poses in seed.items()} for seed in submission.seeds]


@settings(max_examples=300, deadline=None)
@given(edits=EDITS)
def test_damaged_json_files_are_refused_with_problems_or_read_as_they_are(
    edits: list[tuple[int, int, int]],
) -> None:
    damaged = _damaged(json.dumps(_document()).encode(), edits)
    submission = _loaded_or_refused(damaged, "submission.json")
    if submission is not None:
        held = _json_as_read(damaged)
        assert submission.metadata == held.metadata
        assert _poses_lists(submission) == _poses_lists(held)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(edits=EDITS, protocol=st.sampled_from([2, 4, 5]))
def test_damaged_navsim_pickles_are_refused_with_problems_or_load_whole(
    devkit_classes: None, edits: list[tuple[int, int, int]], protocol: int
) -> None:
    predictions = {t: Trajectory(_poses(i), TrajectorySampling()) for i, t in enumerate(TOKENS)}
    # A plain team name: nothing in the file is a method or a link, however damaged.
    valid = _navsim_pickle(predictions, protocol, team_name="Great Planner")
    submission = _loaded_or_refused(_damaged(valid, edits), "submission.pkl")
    if submission is not None:
        # Every trajectory written is there, with poses a scorer can take. There is no reading of the values to
        # compare with: numpy's own unpickler, fed a damaged array, refuses details the loader ignores (the
        # array's pickle version, the type code it starts from) or fails inside numpy.
        assert [len(seed) for seed in submission.seeds] == [len(TOKENS)]
        for poses in submission.seeds[0].values():
            assert poses.shape == (8, 3) and poses.dtype == np.float64 and np.isfinite(poses).all()
        metadata = submission.metadata
        assert (metadata.method, metadata.tech_report_url, metadata.code_url) == ("", "", "")


@settings(max_examples=300, deadline=None)
@given(data=st.binary(min_size=1, max_size=300).map(lambda tail: b"\x80" + tail))
def test_random_pickle_streams_are_refused_with_problems(data: bytes) -> None:
    # Always refused: a submission that loads needs the key "predictions", which random bytes never spell.
    with pytest.raises(SubmissionError) as refused:
        load_submission(data, "random.pkl")
    _assert_problems(refused.value)


def test_declared_sizes_beyond_the_stream_are_refused_before_anything_is_allocated() -> None:
    huge_memo = b"\x80\x04N" + b"r" + (2**30).to_bytes(4, "little") + b"."  # LONG_BINPUT 2**30
    huge_bytes = b"\x80\x04" + b"\x8e" + (2**40).to_bytes(8, "little") + b"abc."  # BINBYTES8 of 2**40 bytes
    for data, reason in ((huge_memo, "memo index 1073741824 out of sequence"), (huge_bytes, "only 4 remain")):
        with pytest.raises(SubmissionError) as refused:
            load_submission(data, "crafted.pkl")
        assert reason in refused.value.problems[0].message


def test_deeply_nested_json_is_refused_with_a_problem() -> None:
    nested = b'{"predictions": {"a1": ' + b"[" * 100_000 + b"]" * 100_000 + b"}}"
    with pytest.raises(SubmissionError) as refused:
        load_submission(nested, "deep.json")
    assert "nested too deeply" in refused.value.problems[0].message


# What a file is, and how much of it is read ------------------------------------------------------


def _refusal(data: bytes, name: str = "entry.pkl", limit: ContentLimit = UNSPLIT_LIMIT) -> str:
    with pytest.raises(SubmissionError) as refused:
        load_submission(data, name, limit)
    [problem] = refused.value.problems
    return problem.message


def _zip(data: bytes) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("submission.json", data)
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("data", "words"),
    [
        (lambda: _zip(json.dumps(_document()).encode()), "entry.pkl is a zip archive, not a submission"),
        (lambda: bz2.compress(json.dumps(_document()).encode()), "entry.pkl is bzip2, not a submission"),
        (lambda: b"\x28\xb5\x2f\xfd" + bytes(16), "entry.pkl is zstd"),
        (lambda: pickle.dumps({"predictions": {}}, protocol=0), "entry.pkl is text starting '(dp0"),
        (lambda: b"token,x,y,heading\n", "entry.pkl is text starting 'token,x,y,heading"),
        (lambda: bytes(range(256)), "entry.pkl is data starting with the bytes 00 01 02 03 04 05 06 07"),
        (
            lambda: gzip.compress(gzip.compress(b"{}")),
            "entry.pkl is gzip holding gzip (compress the file once)",
        ),
        (
            lambda: lzma.compress(gzip.compress(b"{}")),
            "entry.pkl is xz holding gzip (compress the file once)",
        ),
        (lambda: gzip.compress(_zip(b"{}")), "entry.pkl is gzip holding a zip archive"),
    ],
)
def test_a_file_of_another_kind_is_named_by_what_it_is(data: Callable[[], bytes], words: str) -> None:
    message = _refusal(data())
    assert message.startswith(words) and "navsim-lb JSON or a NAVSIM submission pickle" in message, message


def test_the_kind_is_read_from_the_bytes_whatever_the_name() -> None:
    document = json.dumps(_document()).encode()
    for data in (
        document,
        b"\xef\xbb\xbf" + document,
        document.decode().encode("utf-16"),
        gzip.compress(document),
    ):
        assert list(load_submission(data, "entry.pkl").seeds[0]) == TOKENS
    assert file_kind(pickle.dumps({}, protocol=4)) == "a pickle (protocol 4)"
    assert file_kind(b"  \n[1]") == "JSON"


@pytest.mark.parametrize("compress", [gzip.compress, lzma.compress])
def test_a_compressed_file_cut_short_is_refused_as_such(compress: Callable[[bytes], bytes]) -> None:
    data = compress(json.dumps(_document()).encode())
    assert "the stream ends early: the file was cut short" in _refusal(data[: len(data) // 2])


def _largest_valid_files(tokens: list[str]) -> dict[str, bytes]:
    """MAX_SEEDS seeds of the given tokens, in the most bytes each form takes: JSON indented by 4 with every
    number at its longest, and a protocol-2 pickle of float64 (each array's bytes written as latin-1 text)."""
    poses = np.full((8, 3), -1.2345678901234567e-300)
    seeds = [{token: poses.tolist() for token in tokens} for _ in range(MAX_SEEDS)]
    rng = np.random.default_rng(0)
    sampling = TrajectorySampling()
    trajectories = [
        {token: Trajectory(rng.normal(size=(8, 3)) * 1e3, sampling) for token in tokens}
        for _ in range(MAX_SEEDS)
    ]
    return {
        "json": json.dumps(_document(predictions=seeds, authors="\U0001f600" * 1000), indent=4).encode(),
        "pickle": _navsim_pickle(trajectories, 2, authors="\U0001f600" * 1000),
    }


def test_the_content_limit_holds_the_largest_valid_file_of_the_split(devkit_classes: None) -> None:
    tokens = [f"{index:016x}" for index in range(50)]
    limit = ContentLimit.for_tokens(tokens)
    headers = _largest_valid_files([])  # the same files without a token: metadata, format, sampling
    for form, data in _largest_valid_files(tokens).items():
        # Each part within its own bound (the header's slack would hide a per-token bound too small), so the
        # whole within the limit; and such a file loads under it, compressed.
        assert len(headers[form]) <= HEADER_BYTES_BOUND, form
        assert len(data) - len(headers[form]) <= limit.bytes - HEADER_BYTES_BOUND, form
        submission = load_submission(lzma.compress(data, preset=0), "entry", limit)
        assert len(submission.seeds) == MAX_SEEDS and not validate_submission(submission, tokens), form
    assert limit.bytes < ContentLimit.for_tokens([*tokens, "f" * 16]).bytes  # it follows the split


def test_content_past_the_limit_is_refused_as_it_inflates_naming_the_limit_and_why() -> None:
    tokens = [f"{index:016x}" for index in range(50)]
    limit = ContentLimit.for_tokens(tokens)
    blank = b'{"predictions": ' + b" " * (limit.bytes + 1)
    for data, verb in ((blank, "is"), (gzip.compress(blank, 1), "(gzip) decompresses to")):
        message = _refusal(data, limit=limit)
        assert message.startswith(f"entry.pkl {verb} more than {limit.bytes:,} bytes"), message
        assert f"50 tokens x at most {MAX_SEEDS} seeds x 8 poses" in message
    assert load_submission(json.dumps(_document()).encode(), "entry", ContentLimit.for_tokens(TOKENS))


def test_more_seeds_than_a_submission_holds_is_a_problem() -> None:
    seeds = [{token: _poses(seed).tolist() for token in TOKENS} for seed in range(MAX_SEEDS + 1)]
    submission = load_submission(json.dumps(_document(predictions=seeds)).encode())
    [problem] = validate_submission(submission, TOKENS)
    assert (problem.field, problem.message) == (
        "predictions",
        f"{MAX_SEEDS + 1} seeds: a submission holds at most 32",
    )


def test_a_bomb_shaped_like_json_is_refused_at_the_limit_holding_little_of_it_in_memory() -> None:
    # However large the split's limit, what inflates past a small buffer waits on disk until the end: a bomb
    # costs that buffer, not the limit (zlib's output is Python bytes, which tracemalloc sees).
    limit = ContentLimit(256 << 20, "a limit as large as a big split's")
    bomb = gzip_bomb(JSON_START, ord(" "), 512 << 20)
    tracemalloc.start()
    try:
        message = _refusal(bomb, limit=limit)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert message.startswith("entry.pkl (gzip) decompresses to more than 268,435,456 bytes"), message
    assert peak < 16 << 20, f"refusing the bomb held {peak / 2**20:.0f} MiB"
