"""Two-stage submissions: NAVSIM v2's pickle read without running it, our JSON of it, seeds and stage coverage."""

from __future__ import annotations

import json
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from scorer.submission import (
    SubmissionError,
    load_submission,
    load_two_stage_submission,
    two_stage_coverage_problems,
)
from scorer.two_stage.split import read_two_stage_split

FIXTURE = Path(__file__).parent / "fixtures" / "epdms-two-stage"
SPLIT = read_two_stage_split(FIXTURE / "two_stage.json")


def _json_document() -> dict[str, Any]:
    document: dict[str, Any] = json.loads((FIXTURE / "submissions" / "human.json").read_text())
    return document


def _refused(document: dict[str, Any]) -> list[tuple[str | None, str | None, str]]:
    with pytest.raises(SubmissionError) as raised:
        load_two_stage_submission(json.dumps(document).encode(), "two.json")
    return [(problem.token, problem.field, problem.message) for problem in raised.value.problems]


def test_the_navsim_v2_pickle_and_its_json_hold_the_same_poses() -> None:
    from_pickle = load_two_stage_submission((FIXTURE / "submissions" / "human.pkl").read_bytes(), "human.pkl")
    from_json = load_two_stage_submission((FIXTURE / "submissions" / "human.json").read_bytes())
    assert from_pickle.metadata.team_name == from_json.metadata.team_name == "refcheck"
    assert from_pickle.metadata.country == "none"  # the pickle's key is "country / region"
    for stage, tokens in (("first_stage", SPLIT.stage_one_tokens), ("second_stage", SPLIT.stage_two_tokens)):
        pickled, written = getattr(from_pickle, stage), getattr(from_json, stage)
        assert len(pickled) == len(written) == 1
        assert list(pickled[0]) == list(written[0]) == list(tokens)  # submission order is kept
        for token in tokens:
            assert pickled[0][token].shape == (8, 3)
            assert np.array_equal(pickled[0][token], written[0][token])
    assert (
        two_stage_coverage_problems(
            from_pickle.first_stage, from_pickle.second_stage, SPLIT.stage_one_tokens, SPLIT.stage_two_tokens
        )
        == []
    )


def test_the_one_stage_loader_points_a_two_stage_file_elsewhere() -> None:
    with pytest.raises(SubmissionError, match="two-stage"):
        load_submission((FIXTURE / "submissions" / "human.pkl").read_bytes(), "human.pkl")
    with pytest.raises(SubmissionError, match="two-stage submissions are scored under different"):
        load_submission((FIXTURE / "submissions" / "human.json").read_bytes(), "human.json")


def test_several_seeds_are_one_dict_per_list_each() -> None:
    document = _json_document()
    for field in ("first_stage_predictions", "second_stage_predictions"):
        first = document[field][0]
        document[field] = [first, {token: (np.array(poses) * 0.5).tolist() for token, poses in first.items()}]
    submission = load_two_stage_submission(json.dumps(document).encode())
    assert len(submission.first_stage) == len(submission.second_stage) == 2
    token = SPLIT.stage_two_tokens[3]
    assert np.array_equal(submission.second_stage[1][token], submission.second_stage[0][token] * 0.5)


def test_the_stages_must_have_as_many_seeds() -> None:
    document = _json_document()
    document["second_stage_predictions"] *= 2
    assert _refused(document) == [
        (
            None,
            "second_stage_predictions",
            "2 seed(s), but first_stage_predictions has 1: each seed is one dict in each list",
        )
    ]


def test_problems_name_the_stage_and_the_token() -> None:
    document = _json_document()
    synthetic = SPLIT.stage_two_tokens[0]
    document["second_stage_predictions"][0][synthetic] = [[0.0, 0.0]] * 8
    del document["first_stage_predictions"]
    document["predictions"] = {}
    assert _refused(document) == [
        (None, "predictions", "unknown field"),
        (
            None,
            "first_stage_predictions",
            "must be an object token -> poses, or a non-empty list of them (one per seed)",
        ),
        (
            synthetic,
            f"second_stage_predictions[{synthetic!r}]",
            "expected 8 poses of [x, y, heading], got shape (8, 2)",
        ),
    ]


def test_coverage_lists_missing_and_extra_tokens_per_stage() -> None:
    submission = load_two_stage_submission((FIXTURE / "submissions" / "human.json").read_bytes())
    first, second = dict(submission.first_stage[0]), dict(submission.second_stage[0])
    missing_one, missing_two = SPLIT.stage_one_tokens[1], SPLIT.stage_two_tokens[7]
    del first[missing_one], second[missing_two]
    second["f" * 16] = second[SPLIT.stage_two_tokens[0]]  # a logged-frame token submitted as stage two
    first[SPLIT.stage_two_tokens[0]] = first[SPLIT.stage_one_tokens[0]]  # a synthetic token in stage one
    problems = two_stage_coverage_problems([first], [second], SPLIT.stage_one_tokens, SPLIT.stage_two_tokens)
    assert [(problem.token, problem.field, problem.message) for problem in problems] == [
        (missing_one, "first_stage_predictions", "token of the split is missing"),
        (SPLIT.stage_two_tokens[0], "first_stage_predictions", "token is not in the split"),
        (missing_two, "second_stage_predictions", "token of the split is missing"),
        ("f" * 16, "second_stage_predictions", "token is not in the split"),
    ]


def test_an_unreadable_file_keeps_each_stages_tokens_for_coverage() -> None:
    document = _json_document()
    token = SPLIT.stage_one_tokens[0]
    document["first_stage_predictions"][0][token] = "not poses"
    with pytest.raises(SubmissionError) as raised:
        load_two_stage_submission(json.dumps(document).encode())
    assert raised.value.seed_tokens == [list(SPLIT.stage_one_tokens)]
    assert raised.value.second_stage_tokens == [list(SPLIT.stage_two_tokens)]


def test_a_two_stage_pickle_with_foreign_globals_is_refused() -> None:
    data = pickle.dumps({"first_stage_predictions": [{"a" * 16: print}], "second_stage_predictions": [{}]})
    with pytest.raises(SubmissionError, match="builtins.print, which a NAVSIM submission never holds"):
        load_two_stage_submission(data, "evil.pkl")
