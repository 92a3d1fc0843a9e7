"""The streamed JSON reader gives what `json.loads` gives, bit for bit, wherever the chunks of the file end,
and places an error where `json.loads` places it."""

from __future__ import annotations

import io
import json
import math
from typing import Any

import numpy as np
import pytest

import scorer.json_stream
from scorer.json_stream import JsonStreamError, read_json

STREAMED = {"predictions"}


def _pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    return dict(pairs)


def _read(data: bytes) -> Any:
    return read_json(io.BytesIO(data), STREAMED, lambda value: ("leaf", value), _pairs, 1 << 20)


def _as_loads_reads(data: bytes) -> Any:
    """What the streamed reader must give: json.loads's document, each streamed member marked as a leaf."""
    document = json.loads(data, object_pairs_hook=_pairs)
    predictions = document.get("predictions")
    seeds = predictions if isinstance(predictions, list) else [predictions]
    marked = [
        {token: ("leaf", poses) for token, poses in seed.items()} if isinstance(seed, dict) else seed
        for seed in seeds
    ]
    document["predictions"] = marked if isinstance(predictions, list) else marked[0]
    return document


def _documents() -> list[bytes]:
    rng = np.random.default_rng(7)
    poses = [(rng.normal(size=(8, 3)) * 10.0 ** rng.integers(-300, 300)).tolist() for _ in range(4)]
    seed = {
        "tök\u00e9n": poses[0],
        'a"b\\c': poses[1],
        "😀": [[1, 2, 3]] * 8,
        "x": [[math.nan, math.inf, -0.0]],
    }
    document = {"format": "f", "authors": "Ünï ☃", "predictions": [seed, {"y": poses[2]}, 3], "z": [1e-320]}
    return [
        json.dumps(document).encode(),
        json.dumps(document, indent=3).encode(),
        json.dumps({**document, "predictions": seed}, ensure_ascii=False).encode(),
        json.dumps({**document, "predictions": seed}).encode("utf-16"),
        b"\xef\xbb\xbf" + json.dumps({"predictions": {}}).encode(),
        b' { "predictions" : [ ] , "a" : 12345678901234567890 } ',
    ]


@pytest.mark.parametrize("chunk", [1, 3, 7, 1 << 16])
def test_what_is_read_is_what_json_loads_reads_wherever_the_chunks_end(
    chunk: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(scorer.json_stream, "READ_BYTES", chunk)
    for data in _documents():
        read, expected = _read(data), _as_loads_reads(data)
        # repr tells -0.0 from 0.0 and keeps every digit of every float; NaN is compared by its text.
        assert repr(read) == repr(expected), data[:80]


@pytest.mark.parametrize(
    "data",
    [
        b'{"predictions": {"a": [1, 2}}',
        b'{"predictions": {"a": 1,}, "b": 2}',
        b'{"a": 1}\n\n  {"b": 2}',
        b'{"a" 1}',
        b'{"predictions": [{"a": 1} {"b": 2}]}',
        b'{"a": "unterminated',
        b"",
        b'\n\n{"predictions": {"a": [1, 2, 3]}, "b": tru}',
    ],
)
def test_an_error_is_placed_where_json_loads_places_it(data: bytes, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(scorer.json_stream, "READ_BYTES", 4)
    with pytest.raises(json.JSONDecodeError) as expected:
        json.loads(data)
    with pytest.raises(JsonStreamError) as found:
        _read(data)
    assert str(found.value).split(": line ")[1] == str(expected.value).split(": line ")[1], (found, expected)


def test_a_value_read_whole_is_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(scorer.json_stream, "READ_BYTES", 16)
    with pytest.raises(JsonStreamError, match="a value longer than 100 characters"):
        read_json(io.BytesIO(b'{"authors": "' + b"a" * 1000 + b'"}'), STREAMED, lambda v: v, _pairs, 100)
