"""The stage mapping of a two-stage split: `<split>/two_stage.json` (docs/scene-format.md, "Two-stage splits").

NAVSIM's navhard config holds it as `reactive_all_mapping`, a list of `[orig, prev, [[now2, prev2], ...]]`:
a logged frame, the logged frame 0.5 s before it, and synthetic pairs (17-character tokens) that start 4 s
and 3.5 s after them. The official script trusts the list as it comes (a repeated entry silently replaces
the earlier one, a token in two places gets two weights of which the last write wins); this reader refuses
anything that would make a token's group or role ambiguous, naming the entry and the token, so that the
aggregation can index every token by exactly one place.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scorer.human import is_synthetic
from scorer.scene import scene_paths

SPLIT_FORMAT = "navsim-lb/two-stage-split"
SPLIT_VERSION = 1
MAPPING_FILE = "two_stage.json"
# Fields the generator of a split writes for people (per-token provenance); the engine never reads them.
DESCRIPTIVE_FIELDS = frozenset({"generator", "scenes"})
TOKEN_LIST_FIELDS = ("stage_one_tokens", "stage_two_tokens")
MAX_LISTED_PROBLEMS = 20


class TwoStageSplitError(ValueError):
    """A `two_stage.json` that cannot be used; the message names the file, the entry and the token."""


@dataclass(frozen=True)
class StageGroup:
    """One mapping entry: the stage-one tokens `original` and `previous` and the synthetic `pairs` (now2, prev2).

    `now2` starts where `original`'s plan would have taken the ego 4 s later and is weighted against
    `original`'s submitted endpoint; `prev2` likewise against `previous` (3.5 s after it).
    """

    original: str
    previous: str
    pairs: tuple[tuple[str, str], ...]

    @property
    def tokens(self) -> tuple[str, ...]:
        """Return every token of the entry: orig, prev, then each pair's now2 and prev2."""
        return (self.original, self.previous, *(token for pair in self.pairs for token in pair))

    @property
    def now_tokens(self) -> tuple[str, ...]:
        """Return the pairs' first tokens (now2): the stage two of `original`."""
        return tuple(now for now, _ in self.pairs)

    @property
    def previous_tokens(self) -> tuple[str, ...]:
        """Return the pairs' second tokens (prev2): the stage two of `previous`."""
        return tuple(previous for _, previous in self.pairs)


@dataclass(frozen=True)
class TwoStageSplit:
    """A split's stage mapping (None where the split ships `reactive_all_mapping: null`) and its stage tokens."""

    groups: tuple[StageGroup, ...] | None
    stage_one_tokens: tuple[str, ...]
    stage_two_tokens: tuple[str, ...]


def _entry_of(index: int, entry: Any, problems: list[str]) -> StageGroup | None:
    """Return mapping entry `index` as a StageGroup, or record why it is not one."""
    where = f"reactive_all_mapping[{index}]"
    if not (isinstance(entry, list) and len(entry) == 3 and isinstance(entry[2], list)):
        problems.append(f"{where}: must be [orig, prev, [[now2, prev2], ...]]")
        return None
    original, previous, pairs = entry
    if not pairs:
        problems.append(f"{where}: has no synthetic pairs")
        return None
    stage_one = [(f"{where}[0]", original), (f"{where}[1]", previous)]
    if not all(isinstance(pair, list) and len(pair) == 2 for pair in pairs):
        problems.append(f"{where}[2]: every pair must be [now2, prev2]")
        return None
    stage_two = [
        (f"{where}[2][{p}][{i}]", token) for p, pair in enumerate(pairs) for i, token in enumerate(pair)
    ]
    readable = True
    for field, token in stage_one + stage_two:
        if not isinstance(token, str) or not token:
            problems.append(f"{field}: a token must be non-empty text, got {token!r}")
            readable = False
    if not readable:
        return None
    for field, token in stage_one:
        if is_synthetic(token):
            problems.append(f"{field}: token {token} has 17 characters (synthetic), expected a logged frame")
    for field, token in stage_two:
        if not is_synthetic(token):
            problems.append(f"{field}: token {token} is not synthetic (17 characters)")
    return StageGroup(original, previous, tuple((now, prev) for now, prev in pairs))


def _places(groups: Iterable[StageGroup]) -> dict[str, list[str]]:
    """Return token -> every place of the mapping that names it."""
    places: dict[str, list[str]] = {}
    for index, group in enumerate(groups):
        where = f"reactive_all_mapping[{index}]"
        places.setdefault(group.original, []).append(f"{where} orig")
        places.setdefault(group.previous, []).append(f"{where} prev")
        for pair, (now, previous) in enumerate(group.pairs):
            places.setdefault(now, []).append(f"{where} pair {pair} now2")
            places.setdefault(previous, []).append(f"{where} pair {pair} prev2")
    return places


def _listed_tokens(
    document: dict[str, Any], field: str, expected: tuple[str, ...] | None, problems: list[str]
) -> tuple[str, ...] | None:
    """Return a stage's token list as the file gives it (None when absent), checked against the mapping's."""
    if field not in document:
        return None
    listed = document[field]
    if not (isinstance(listed, list) and all(isinstance(token, str) for token in listed)):
        problems.append(f"{field}: must be a list of tokens")
        return None
    if len(set(listed)) != len(listed):
        problems.append(f"{field}: lists a token more than once")
    if expected is not None:
        problems += [
            f"{field}: token {token} of the mapping is not listed"
            for token in sorted(set(expected) - set(listed))
        ]
        problems += [
            f"{field}: token {token} is not in the mapping" for token in sorted(set(listed) - set(expected))
        ]
    return tuple(listed)


def parse_two_stage_split(document: Any, source: str = MAPPING_FILE) -> TwoStageSplit:
    """Return the split a `navsim-lb/two-stage-split` document describes; raise TwoStageSplitError listing every
    problem (`source` names the file in the message).

    Stage tokens are the file's `stage_one_tokens` / `stage_two_tokens` when given (they must hold exactly the
    mapping's tokens), else the mapping's in entry order: orig, prev, ...; now2, prev2 of each pair, ....
    """
    if not isinstance(document, dict):
        raise TwoStageSplitError(f"{source}: must be a JSON object")
    problems: list[str] = []
    if document.get("format") != SPLIT_FORMAT:
        problems.append(f"format: must be {SPLIT_FORMAT!r}, got {document.get('format')!r}")
    if document.get("version") != SPLIT_VERSION:
        problems.append(f"version: must be {SPLIT_VERSION}, got {document.get('version')!r}")
    known = {"format", "version", "reactive_all_mapping", *TOKEN_LIST_FIELDS, *DESCRIPTIVE_FIELDS}
    problems += [f"{key}: unknown field" for key in sorted(set(document) - known)]
    if "reactive_all_mapping" not in document:
        problems.append("reactive_all_mapping: missing (write null for a split without one)")
    mapping = document.get("reactive_all_mapping")
    groups: tuple[StageGroup, ...] | None = None
    if mapping is not None and not isinstance(mapping, list):
        problems.append("reactive_all_mapping: must be a list of entries or null")
    elif mapping is not None:
        entries = [_entry_of(index, entry, problems) for index, entry in enumerate(mapping)]
        groups = tuple(entry for entry in entries if entry is not None)
        problems += [
            f"token {token} appears more than once: {', '.join(where)}"
            for token, where in _places(groups).items()
            if len(where) > 1
        ]
    stage_one = tuple(token for group in groups or () for token in (group.original, group.previous))
    stage_two = tuple(token for group in groups or () for pair in group.pairs for token in pair)
    listed_one = _listed_tokens(
        document, "stage_one_tokens", stage_one if groups is not None else None, problems
    )
    listed_two = _listed_tokens(
        document, "stage_two_tokens", stage_two if groups is not None else None, problems
    )
    if problems:
        shown = problems[:MAX_LISTED_PROBLEMS]
        if len(problems) > len(shown):
            shown.append(f"{len(problems) - len(shown)} more problem(s) not listed")
        raise TwoStageSplitError(f"{source}: " + "; ".join(shown))
    return TwoStageSplit(
        groups=groups,
        stage_one_tokens=listed_one if listed_one is not None else stage_one,
        stage_two_tokens=listed_two if listed_two is not None else stage_two,
    )


def read_two_stage_split(path: Path) -> TwoStageSplit:
    """Return the split of a `two_stage.json` file (`parse_two_stage_split`)."""
    try:
        document = json.loads(Path(path).read_bytes())
    except (UnicodeDecodeError, ValueError) as error:
        raise TwoStageSplitError(f"{path}: not valid JSON: {error}") from None
    return parse_two_stage_split(document, str(path))


def load_two_stage_split(split_dir: Path, tokens: Iterable[str] | None = None) -> TwoStageSplit:
    """Return the stage mapping of the split at `split_dir`, every token of which must be one of the split's:
    its scene files, or `tokens` where the directory holds only some of them (a worker's copy of a split in an
    object store, whose tokens its manifest lists, in token order).

    Where the mapping is null and the file lists no stage tokens, the split's scenes are staged as NAVSIM
    stages them, by token length: 17 characters are synthetic (stage two), the others logged (stage one).
    """
    path = Path(split_dir) / MAPPING_FILE
    if not path.is_file():
        raise TwoStageSplitError(f"{split_dir}: no {MAPPING_FILE}: not a two-stage split")
    split = read_two_stage_split(path)
    scenes = dict.fromkeys(scene_paths(split_dir) if tokens is None else tokens)
    unknown = [token for token in split.stage_one_tokens + split.stage_two_tokens if token not in scenes]
    if unknown:
        listed = ", ".join(unknown[:MAX_LISTED_PROBLEMS])
        more = f" and {len(unknown) - MAX_LISTED_PROBLEMS} more" if len(unknown) > MAX_LISTED_PROBLEMS else ""
        raise TwoStageSplitError(f"{path}: no scene file for token(s) {listed}{more}")
    if split.groups is None and not split.stage_one_tokens and not split.stage_two_tokens:
        return TwoStageSplit(
            groups=None,
            stage_one_tokens=tuple(token for token in scenes if not is_synthetic(token)),
            stage_two_tokens=tuple(token for token in scenes if is_synthetic(token)),
        )
    return split
