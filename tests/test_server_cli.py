"""`navsim-lb db ...` and `navsim-lb admin ...`: migrate, then create a team, tokens and a phase from the shell."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import typer
from fastapi.testclient import TestClient
from server_testing import REFERENCE_DIR, reference_tokens
from typer.testing import CliRunner

from server.cli import register
from server.main import create_app
from server.migrate import head_revision
from server.models import Split
from server.settings import get_settings

Cli = tuple[Callable[..., str], typer.Typer, CliRunner]  # invoke(*args) -> stdout, the app, the runner


@pytest.fixture
def cli(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Cli]:
    monkeypatch.setenv("DATA_DIR", str(tmp_path))
    monkeypatch.setenv("LEADERBOARD_CACHE_SECONDS", "0")
    get_settings.cache_clear()
    app = typer.Typer()
    register(app)
    runner = CliRunner()

    def invoke(*args: str) -> str:
        result = runner.invoke(app, list(args))
        assert result.exit_code == 0, (args, result.output)
        return result.stdout

    yield invoke, app, runner
    get_settings.cache_clear()


def test_migrate_then_administer_from_the_shell(cli: Cli) -> None:
    invoke, app, runner = cli
    refused = runner.invoke(app, ["admin", "create-team", "alpha"])
    assert refused.exit_code == 2 and "run `navsim-lb db upgrade`" in " ".join(refused.output.split())
    invoke("db", "upgrade")
    assert f"current: {head_revision()}" in invoke("db", "current")
    team_id = int(invoke("admin", "create-team", "alpha", "--member", "Ann", "--affiliation", "Lab").strip())
    team_token = invoke("admin", "create-token", "--team", "alpha").strip()
    admin_token = invoke("admin", "create-token", "--admin", "--name", "ops", "--expires-days", "1").strip()
    assert team_token.startswith("nlb_") and admin_token.startswith("nlb_")
    assert runner.invoke(app, ["admin", "create-token", "--team", "nobody"]).exit_code == 2

    server = create_app(get_settings(), enqueue=lambda _: None)
    with server.state.session_factory() as session:
        session.add(Split(name="ref", directory=str(REFERENCE_DIR), content_hash="0" * 64, token_count=40))
        session.commit()
    invoke("admin", "create-phase", "test", "--split", "ref", "--per-day", "5")
    with TestClient(server) as client:
        me = client.get("/api/v1/me", headers={"Authorization": f"Bearer {team_token}"}).json()
        assert me["team"] == "alpha" and {(q["quota"], q["limit"]) for q in me["quotas"]} >= {("per_day", 5)}
        audit = client.get("/api/v1/admin/audit", headers={"Authorization": f"Bearer {admin_token}"}).json()
        assert [entry["action"] for entry in reversed(audit)] == [
            "create_team",
            "create_token",
            "create_token",
            "create_phase",
        ]
        assert all(entry["actor"] == "command line" for entry in audit)
        assert audit[-1]["target_id"] == str(team_id)
    server.state.engine.dispose()
    invoke("db", "downgrade", "base")
    assert "current: none" in invoke("db", "current")


def test_register_split_queues_its_baselines(cli: Cli, tmp_path: Path) -> None:
    invoke, _, _ = cli
    invoke("db", "upgrade")
    public = tmp_path / "public.txt"
    public.write_text("\n".join(reference_tokens()[:10]))
    invoke("admin", "register-split", "ref", str(REFERENCE_DIR), "--public-tokens", str(public))
    admin = {"Authorization": f"Bearer {invoke('admin', 'create-token', '--admin').strip()}"}
    server = create_app(get_settings(), enqueue=lambda _: None)
    with TestClient(server) as client:
        splits = client.get("/api/v1/splits").json()
        assert splits[0]["subsets"] == {"public": 10, "private": 30, "all": 40}
        body = {"name": "ref-api", "directory": str(REFERENCE_DIR), "public_tokens": reference_tokens()[:10]}
        assert client.post("/api/v1/admin/splits", json=body, headers=admin).status_code == 201
        audit = client.get("/api/v1/admin/audit", headers=admin).json()
    server.state.engine.dispose()
    # The command line and the API register a split through one service: the audit log says the same.
    by_api, by_cli = (entry for entry in audit if entry["action"] == "register_split")
    assert (by_cli["actor"], by_api["actor"].startswith("admin token")) == ("command line", True)
    assert (
        len(by_cli["details"]["baseline_submissions"]) == len(by_api["details"]["baseline_submissions"]) == 2
    )
    for entry in (by_cli, by_api):
        del entry["details"]["baseline_submissions"]
    assert by_cli["details"] == by_api["details"]
    assert by_cli["details"]["content_hash"] and by_cli["details"]["public_tokens"] == 10
