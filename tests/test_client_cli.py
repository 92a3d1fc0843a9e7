"""`navsim-lb validate` gives the server's verdict locally; `navsim-lb submit` says when no server answers."""

from __future__ import annotations

import json
import math
from pathlib import Path

from server_testing import REFERENCE_DIR, REFERENCE_SUBMISSIONS, World
from typer.testing import CliRunner

from navsim_lb.cli import app

HUMAN = REFERENCE_SUBMISSIONS / "human.json"


def _broken(path: Path) -> Path:
    """Write the human submission with a missing token, a wrong shape and a non-finite value."""
    document = json.loads(HUMAN.read_bytes())
    tokens = sorted(document["predictions"])
    del document["predictions"][tokens[0]]
    document["predictions"][tokens[1]] = document["predictions"][tokens[1]][:5]
    document["predictions"][tokens[2]][3][0] = math.inf
    path.write_text(json.dumps(document, allow_nan=True))
    return path


def test_validate_accepts_what_the_server_accepts(world: World) -> None:
    local = CliRunner().invoke(app, ["validate", str(HUMAN), "--split", str(REFERENCE_DIR)])
    remote = world.client.post(
        "/api/v1/submissions:validate",
        headers=world.team_headers(),
        files={"file": (HUMAN.name, HUMAN.read_bytes())},
    )
    assert (local.exit_code, remote.status_code) == (0, 200), local.output
    assert "valid" in local.output and remote.json()["sha256"][:12] in local.output


def test_validate_lists_the_problems_the_server_lists(world: World, tmp_path: Path) -> None:
    broken = _broken(tmp_path / "broken.json")
    local = CliRunner().invoke(app, ["validate", str(broken), "--split", str(REFERENCE_DIR)])
    remote = world.client.post(
        "/api/v1/submissions:validate",
        headers=world.team_headers(),
        files={"file": (broken.name, broken.read_bytes())},
    )
    assert (local.exit_code, remote.status_code) == (2, 422)
    problems = remote.json()["problems"]
    assert len(problems) == 3
    output = " ".join(local.output.split())  # rich wraps long lines
    for problem in problems:
        assert problem["token"] in output and problem["message"] in output, problem


def test_validate_names_a_missing_split(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["validate", str(HUMAN), "--split", str(tmp_path)])
    assert result.exit_code == 2 and "no scenes/ directory" in " ".join(result.output.split())


def test_submit_without_a_reachable_server_says_so(tmp_path: Path) -> None:
    result = CliRunner().invoke(
        app,
        ["submit", str(HUMAN), "--server", "http://127.0.0.1:9", "--token", "nlb_x"],
        env={"COLUMNS": "200"},
    )
    assert result.exit_code == 2 and "cannot talk to http://127.0.0.1:9" in result.output


def test_submit_prints_scores_in_percent_as_the_pages_do(world: World) -> None:
    from rich.console import Console
    from server_testing import submit_scored, uniform

    from navsim_lb.client import results_table

    submission_id = submit_scored(world, world.team_id, b"a", [uniform(0.9525)], "Tie")
    state = world.client.get(f"/api/v1/submissions/{submission_id}", headers=world.team_headers()).json()
    console = Console(width=120, record=True)
    console.print(results_table(state))
    text = console.export_text()
    assert "scores in %" in text and "PDMS v1.1" in text
    assert " 95.3 " in text and "0.952" not in text  # the pages' figure, not the fraction
