"""A two-stage split on the server: registering a directory with `two_stage.json` makes a two-stage split, whose
runs are scored under NAVSIM's two-stage EPDMS (`server.runs.RUN_VERSIONS`), and whose uploads must be in a
two-stage form."""

from __future__ import annotations

import gzip
import json
import shutil
from datetime import timedelta
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from server_testing import REFERENCE_DIR, REFERENCE_SUBMISSIONS, World

from scorer.submission import SubmissionMetadata, TwoStageSubmission, dump_two_stage_submission_json
from scorer.two_stage.split import MAPPING_FILE, load_two_stage_split
from server.db import transaction
from server.models import SplitKind, Submission, utc_now
from server.runs import RUN_VERSIONS, run_versions
from server.services.errors import Conflict
from server.services.splits import create_phase, register_split, split_tokens
from server.storage import read_trajectories

TWO_STAGE_DIR = Path(__file__).parent / "fixtures" / "epdms-two-stage-reactive"
FULL_REFERENCE_PICKLE = Path(__file__).parent / "fixtures" / "epdms-two-stage" / "submissions" / "human.pkl"
STAGES = load_two_stage_split(TWO_STAGE_DIR)
PHASE = "navhard"


@cache
def family_poses(family: str) -> dict[str, np.ndarray]:
    """Return a reference family's submitted poses of the 36 excerpt tokens."""
    with gzip.open(TWO_STAGE_DIR / "predictions.json.gz", "rt") as handle:
        predictions: dict[str, dict[str, Any]] = json.load(handle)
    return {token: np.array(poses) for token, poses in predictions[family].items()}


def family_submission(family: str, seeds: int = 1) -> TwoStageSubmission:
    """Return a family's two-stage submission of the excerpt; seed i > 0 moves every pose i x 0.3 m ahead."""
    poses = family_poses(family)
    shifted = [
        {token: value + [0.3 * seed, 0.0, 0.0] for token, value in poses.items()} for seed in range(seeds)
    ]
    first, second = (
        tuple({token: seed[token] for token in tokens} for seed in shifted)
        for tokens in (STAGES.stage_one_tokens, STAGES.stage_two_tokens)
    )
    return TwoStageSubmission(SubmissionMetadata(method=family), first, second)


def add_two_stage_phase(world: World) -> None:
    """Register the excerpt as a two-stage split with an open phase `PHASE` ("test" stays the default)."""
    with transaction(world.factory) as session:
        split = register_split(session, PHASE, TWO_STAGE_DIR)
        create_phase(session, PHASE, split, opens_at=utc_now() - timedelta(days=30))


def post(world: World, data: bytes, name: str, phase: str = PHASE) -> Any:
    return world.client.post(
        "/api/v1/submissions",
        headers=world.team_headers(),
        files={"file": (name, data)},
        data={"phase": phase},
    )


def test_a_directory_with_a_stage_mapping_registers_as_a_two_stage_split(world: World) -> None:
    with transaction(world.factory) as session:
        two_stage = register_split(session, "navhard-excerpt", TWO_STAGE_DIR)
        one_stage = register_split(session, "reference-scenes", REFERENCE_DIR)
        assert (two_stage.kind, one_stage.kind) == (SplitKind.two_stage, SplitKind.log_replay)
        assert run_versions(two_stage) == ("v2.2-two-stage",)
        assert run_versions(one_stage) == ("v1.0", "v1.1", "v2.2")
        assert split_tokens(two_stage) == STAGES.stage_one_tokens + STAGES.stage_two_tokens
        assert two_stage.token_count == 36 == len(set(split_tokens(two_stage)))
    assert set(RUN_VERSIONS) == set(SplitKind)


def test_a_two_stage_split_is_refused_with_what_is_wrong(world: World, tmp_path: Path) -> None:
    broken = tmp_path / "split"
    shutil.copytree(TWO_STAGE_DIR / "scenes", broken / "scenes")
    document = json.loads((TWO_STAGE_DIR / MAPPING_FILE).read_text())
    document["reactive_all_mapping"][1][0] = "not-a-token"
    (broken / MAPPING_FILE).write_text(json.dumps(document))
    with transaction(world.factory) as session, pytest.raises(Conflict) as refused:
        register_split(session, "broken", broken)
    assert "no scene file for token(s) not-a-token" in refused.value.message
    assert str(tmp_path) not in refused.value.message  # the server's paths stay on the server
    with transaction(world.factory) as session, pytest.raises(Conflict, match="no public and private"):
        register_split(session, "halves", TWO_STAGE_DIR, public_tokens=list(STAGES.stage_one_tokens[:2]))


def test_a_two_stage_upload_is_accepted_with_every_seed_in_the_official_row_order(world: World) -> None:
    add_two_stage_phase(world)
    response = post(world, dump_two_stage_submission_json(family_submission("human", seeds=2)), "two.json")
    assert response.status_code == 202, response.text
    with world.session() as session:
        submission = session.get(Submission, response.json()["id"])
        assert submission is not None
        assert (submission.seed_count, submission.token_count) == (2, 36)
        stored = read_trajectories(world.settings.storage_dir, submission.stored_name, submission.sha256)
    assert stored is not None and len(stored) == 2
    assert list(stored[1]) == [*STAGES.stage_one_tokens, *STAGES.stage_two_tokens]
    token = STAGES.stage_two_tokens[4]
    assert np.array_equal(stored[1][token], family_poses("human")[token] + [0.3, 0.0, 0.0])


def test_missing_and_extra_tokens_are_listed_per_stage_before_anything_is_queued(world: World) -> None:
    add_two_stage_phase(world)
    submission = family_submission("human")
    dropped = STAGES.stage_two_tokens[7]
    del submission.second_stage[0][dropped]
    submission.first_stage[0]["0123456789abcdef"] = submission.first_stage[0][STAGES.stage_one_tokens[0]]
    response = post(world, dump_two_stage_submission_json(submission), "two.json")
    assert response.status_code == 422
    problems = {(p["field"], p["token"], p["message"]) for p in response.json()["problems"]}
    assert problems == {
        ("first_stage_predictions", "0123456789abcdef", "token is not in the split"),
        ("second_stage_predictions", dropped, "token of the split is missing"),
    }
    # NAVSIM's v2 pickle, read without running it: the whole reference's tokens, beyond the excerpt's.
    pickled = post(world, FULL_REFERENCE_PICKLE.read_bytes(), "human.pkl")
    assert pickled.status_code == 422
    extra = {(p["field"], p["message"]) for p in pickled.json()["problems"]}
    # 74 stage-one and 370 stage-two tokens beyond the excerpt: the first 50 listed, the rest counted.
    assert extra == {
        ("first_stage_predictions", "token is not in the split"),
        (None, "394 more problem(s) not listed"),
    }
    assert world.queued == []


def test_an_upload_in_the_other_kinds_form_is_refused_saying_which_form_the_split_takes(world: World) -> None:
    add_two_stage_phase(world)
    one_stage = (REFERENCE_SUBMISSIONS / "human.json").read_bytes()
    refused = post(world, one_stage, "human.json")
    assert refused.status_code == 422
    assert "is a two-stage split: it takes a two-stage submission" in refused.json()["detail"]
    assert "the file is a one-stage submission" in refused.json()["detail"]
    two_stage = dump_two_stage_submission_json(family_submission("human"))
    refused = post(world, two_stage, "two.json", phase="test")
    assert refused.status_code == 422
    assert "is a one-stage split: it takes a one-stage submission" in refused.json()["detail"]
    assert world.queued == []
