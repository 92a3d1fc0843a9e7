"""A two-stage split on the server: registering a directory with `two_stage.json` makes a two-stage split, whose
runs are scored under NAVSIM's two-stage EPDMS (`server.runs.RUN_VERSIONS`), and whose uploads must be in a
two-stage form."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from server_testing import REFERENCE_DIR, World

from scorer.two_stage.split import MAPPING_FILE, load_two_stage_split
from server.db import transaction
from server.models import SplitKind
from server.runs import RUN_VERSIONS, run_versions
from server.services.errors import Conflict
from server.services.splits import register_split, split_tokens

TWO_STAGE_DIR = Path(__file__).parent / "fixtures" / "epdms-two-stage-reactive"
STAGES = load_two_stage_split(TWO_STAGE_DIR)


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
