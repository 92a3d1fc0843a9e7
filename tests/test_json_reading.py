"""`read_json` reads what `json.loads` reads, the same values bit for bit, and refuses what it refuses."""

from __future__ import annotations

import json

import pytest

from scorer.json_reading import read_json

DOCUMENTS = [
    b'{"x": 0.1, "y": [1e-320, 2.2250738585072014e-308, 1.7976931348623157e308, -0.0], "t0_us": 1623456789012345}',
    b'{"human": {"ep": NaN, "speed": Infinity}, "lanes": ["a", "b"]}',  # orjson refuses these
    b'{"lone": "\\ud800"}',
    b"[1e400]",
]


@pytest.mark.parametrize("data", DOCUMENTS)
def test_reads_as_the_standard_library(data: bytes) -> None:
    # Shortest round-trip reprs: equal texts are equal values, types, signs of zero and bits.
    assert json.dumps(read_json(data)) == json.dumps(json.loads(data))


@pytest.mark.parametrize("data", [b'{"x": ', b'{"x": 1}}', b'{"form\xff\xfet": 1}'])
def test_refuses_what_the_standard_library_refuses(data: bytes) -> None:
    with pytest.raises(ValueError):
        json.loads(data)
    with pytest.raises(ValueError):
        read_json(data)
