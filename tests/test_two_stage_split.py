"""The stage mapping of a two-stage split: the reference mapping reads, and every broken rule names its entry."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import pytest

from scorer.two_stage.split import (
    TwoStageSplitError,
    load_two_stage_split,
    parse_two_stage_split,
    read_two_stage_split,
)

FIXTURE = Path(__file__).parent / "fixtures" / "epdms-two-stage"


def _document() -> dict[str, Any]:
    document: dict[str, Any] = json.loads((FIXTURE / "two_stage.json").read_text())
    return document


def test_reference_mapping_reads_with_its_stage_tokens() -> None:
    split = read_two_stage_split(FIXTURE / "two_stage.json")
    document = _document()
    assert split.groups is not None and len(split.groups) == 40
    first = split.groups[0]
    assert [first.original, first.previous] == document["reactive_all_mapping"][0][:2]
    assert [list(pair) for pair in first.pairs] == document["reactive_all_mapping"][0][2]
    assert first.now_tokens == tuple(pair[0] for pair in first.pairs)
    assert first.previous_tokens == tuple(pair[1] for pair in first.pairs)
    assert list(split.stage_one_tokens) == document["stage_one_tokens"]
    assert list(split.stage_two_tokens) == document["stage_two_tokens"]
    assert (len(split.stage_one_tokens), len(split.stage_two_tokens)) == (80, 400)


def test_stage_tokens_default_to_the_mapping_order() -> None:
    document = _document()
    del document["stage_one_tokens"], document["stage_two_tokens"], document["scenes"]
    split = parse_two_stage_split(document)
    assert list(split.stage_one_tokens) == _document()["stage_one_tokens"]
    assert list(split.stage_two_tokens) == _document()["stage_two_tokens"]


def _broken(change: str) -> dict[str, Any]:
    document = _document()
    mapping = document["reactive_all_mapping"]
    first_now = mapping[0][2][0][0]
    if change == "synthetic original":
        mapping[0][0] = first_now
    elif change == "logged now2":
        mapping[1][2][3][0] = mapping[1][0]
    elif change == "repeated entry":
        mapping.append(copy.deepcopy(mapping[0]))
    elif change == "no pairs":
        mapping[2][2] = []
    elif change == "bad pair":
        mapping[2][2][1] = ["only-one"]
    elif change == "not a token":
        mapping[3][1] = 7
    elif change == "unlisted token":
        document["stage_two_tokens"].remove(first_now)
    elif change == "unknown field":
        document["reactive_mapping"] = []
    elif change == "wrong format":
        document["format"] = "navsim-lb/scene"
    return document


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("synthetic original", "reactive_all_mapping[0][0]: token e9b2a5358b4ab7d6c has 17 characters"),
        ("logged now2", "reactive_all_mapping[1][2][3][0]: token 096283870ef87046 is not synthetic"),
        (
            "repeated entry",
            "token 05ef979906eefe4a appears more than once: reactive_all_mapping[0] orig, reactive_all_mapping[40] orig",
        ),
        ("no pairs", "reactive_all_mapping[2]: has no synthetic pairs"),
        ("bad pair", "reactive_all_mapping[2][2]: every pair must be [now2, prev2]"),
        ("not a token", "reactive_all_mapping[3][1]: a token must be non-empty text, got 7"),
        ("unlisted token", "stage_two_tokens: token e9b2a5358b4ab7d6c of the mapping is not listed"),
        ("unknown field", "reactive_mapping: unknown field"),
        ("wrong format", "format: must be 'navsim-lb/two-stage-split'"),
    ],
)
def test_a_broken_mapping_names_its_entry_and_token(change: str, message: str) -> None:
    with pytest.raises(TwoStageSplitError, match="^two_stage.json: ") as raised:
        parse_two_stage_split(_broken(change))
    assert message in str(raised.value)


def test_a_token_in_two_pairs_names_both_places() -> None:
    document = _document()
    mapping = document["reactive_all_mapping"]
    mapping[1][2][0][1] = mapping[0][2][4][1]
    with pytest.raises(TwoStageSplitError) as raised:
        parse_two_stage_split(document)
    assert (
        f"token {mapping[0][2][4][1]} appears more than once: reactive_all_mapping[0] pair 4 prev2, "
        "reactive_all_mapping[1] pair 0 prev2"
    ) in str(raised.value)


def _split_dir(tmp_path: Path, document: dict[str, Any], tokens: list[str]) -> Path:
    (tmp_path / "scenes").mkdir()
    for token in tokens:
        (tmp_path / "scenes" / f"{token}.json").write_text("{}")  # only the names are read here
    (tmp_path / "two_stage.json").write_text(json.dumps(document))
    return tmp_path


def test_every_mapped_token_needs_a_scene_file(tmp_path: Path) -> None:
    document = _document()
    tokens = document["stage_one_tokens"] + document["stage_two_tokens"]
    missing = tokens.pop(7)
    with pytest.raises(TwoStageSplitError, match=f"no scene file for token\\(s\\) {missing}$"):
        load_two_stage_split(_split_dir(tmp_path, document, tokens))


def test_a_null_mapping_stages_the_scenes_by_token_length(tmp_path: Path) -> None:
    """navhard's private test config ships `reactive_all_mapping: null`: no groups, stages as NAVSIM's frame type."""
    document = {"format": "navsim-lb/two-stage-split", "version": 1, "reactive_all_mapping": None}
    split = load_two_stage_split(_split_dir(tmp_path, document, ["b" * 16, "a" * 17, "c" * 16]))
    assert split.groups is None
    assert split.stage_one_tokens == ("b" * 16, "c" * 16)
    assert split.stage_two_tokens == ("a" * 17,)


def test_a_split_without_mapping_file_is_not_two_stage(tmp_path: Path) -> None:
    (tmp_path / "scenes").mkdir()
    with pytest.raises(TwoStageSplitError, match="no two_stage.json: not a two-stage split"):
        load_two_stage_split(tmp_path)
