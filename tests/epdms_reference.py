"""The official NAVSIM v2.2 results (`fixtures/epdms`, README there) as rows with their scenes, read once per
test session: the 40 public scenes and the 102 probe scenes, 13 families each."""

from __future__ import annotations

import gzip
import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from scorer.scene import Scene, load_scene

FIXTURES = Path(__file__).parent / "fixtures"
EPDMS = FIXTURES / "epdms"
# Each expected directory with the scenes its tokens come from.
SOURCES = (
    (EPDMS / "expected", FIXTURES / "reference" / "scenes"),
    (EPDMS / "probes" / "expected", EPDMS / "probes" / "scenes"),
)


@dataclass(frozen=True, eq=False)
class Row:
    """One official result line: its family, the scene file of its token and the line itself."""

    family: str
    scene_path: Path
    line: dict[str, Any]

    @property
    def token(self) -> str:
        return str(self.line["token"])

    @property
    def diagnostics(self) -> dict[str, Any]:
        return dict(self.line["diagnostics"])


@cache
def rows() -> tuple[Row, ...]:
    """Return every official line (1,846), public scenes first, families in name order."""
    found = []
    for expected, scenes in SOURCES:
        for path in sorted(expected.glob("*.v2.2.jsonl.gz")):
            family = path.name.split(".")[0]
            with gzip.open(path, "rt") as handle:
                found += [
                    Row(family, scenes / f"{line['token']}.json.gz", line) for line in map(json.loads, handle)
                ]
    return tuple(found)


@cache
def scene(path: Path) -> Scene:
    """Return the scene at `path`, loaded once."""
    return load_scene(path)
