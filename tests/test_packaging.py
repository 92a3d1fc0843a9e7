"""The wheel, as a user installs it: built from the sources, installed into a fresh virtual environment (not
the checkout), first without extras (the engine and a team's commands), then with `[server]`. The engine-only
install passes `navsim-lb regress`, imports no server library and says which extra draws pictures (`[plot]`);
the full one migrates a database and serves the pages, their assets and the API from the package data alone.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import httpx
import pytest
import typer
from worker_testing import api_answers, free_port, wait_for

from navsim_lb import demo
from navsim_lb.cli import SERVER_COMMANDS, SERVER_EXTRA
from navsim_lb.engine_cli import PLOT_EXTRA
from navsim_lb.processes import child_process
from server import cli as server_cli
from server.migrate import head_revision
from worker import cli as worker_cli

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
SETUPTOOLS = PYPROJECT["tool"]["setuptools"]
# Installed inside the server's package, from the repository's top-level directories.
MAPPED = {"server.web": ROOT / "web", "server.migrations": ROOT / "migrations"}
# What the engine must never pull in: the server's libraries and the command line's.
NOT_ENGINE = (
    "fastapi",
    "starlette",
    "sqlalchemy",
    "celery",
    "pydantic",
    "typer",
    "rich",
    "pandas",
    "matplotlib",
)
# setuptools' warning for such a directory: since version 68, then its older wording.
UNDECLARED = ("is absent from the `packages` configuration", "as data is deprecated")
SOURCES_IGNORED = (
    ".git",
    ".venv",
    ".navsim-lb",
    "__pycache__",
    "*.egg-info",
    "build",
    "tests",
    "benchmarks",
    "data",
)


def _names(app: typer.Typer) -> set[str]:
    commands = {command.name or command.callback.__name__ for command in app.registered_commands}  # type: ignore[union-attr]
    return commands | {group.name for group in app.registered_groups if group.name}


def test_the_package_list_misses_no_package() -> None:
    found = [
        ".".join(init.parent.relative_to(ROOT).parts)
        for top in ("scorer", "server", "worker", "navsim_lb")
        for init in (ROOT / top).rglob("__init__.py")
    ]
    assert sorted(SETUPTOOLS["packages"]) == sorted([*found, *MAPPED])
    assert {name: ROOT / path for name, path in SETUPTOOLS["package-dir"].items()} == MAPPED


def test_the_install_hints_stand_for_exactly_the_server_commands() -> None:
    server_only = typer.Typer()
    for module in (server_cli, worker_cli, demo):
        module.register(server_only)
    assert _names(server_only) == set(SERVER_COMMANDS)


class Build(NamedTuple):
    wheel: Path
    log: str  # pip's verbose output, which holds the build backend's warnings


@pytest.fixture(scope="module")
def build(tmp_path_factory: pytest.TempPathFactory) -> Build:
    """Build the wheel from a copy of the sources (a build in place would leave build/ in the checkout)."""
    sources = tmp_path_factory.mktemp("sources") / "navsim-leaderboard"
    shutil.copytree(ROOT, sources, ignore=shutil.ignore_patterns(*SOURCES_IGNORED))
    out = tmp_path_factory.mktemp("dist")
    # Verbose: without it pip hides what the build backend prints, warnings included.
    command = [sys.executable, "-m", "pip", "wheel", "--verbose", "--no-deps"]
    done = subprocess.run(
        [*command, "--wheel-dir", str(out), str(sources)], check=True, capture_output=True, text=True
    )
    (built,) = out.glob("navsim_leaderboard-*.whl")
    return Build(built, done.stdout + done.stderr)


@pytest.fixture(scope="module")
def wheel(build: Build) -> Path:
    return build.wheel


def test_the_build_takes_no_data_directory_for_an_undeclared_package(build: Build) -> None:
    """A data directory such as web/templates is importable to Python; unless setuptools is told the package data
    is exactly what `package-data` lists, it prints a page-long warning for each one on every `pip install`."""
    warned = [line for line in build.log.splitlines() if any(words in line for words in UNDECLARED)]
    assert warned == []


def test_the_wheel_carries_the_pages_the_migrations_and_the_goldens(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as archive:
        shipped = set(archive.namelist())
    expected = {
        f"{package.replace('.', '/')}/{path.relative_to(directory).as_posix()}"
        for package, directory in MAPPED.items()
        for path in directory.rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }
    expected |= {
        f"scorer/regression/golden/{path.name}" for path in (ROOT / "scorer/regression/golden").iterdir()
    }
    assert any(name.endswith(".html") for name in expected) and any("versions/" in name for name in expected)
    assert expected <= shipped, sorted(expected - shipped)


class Install:
    """A fresh virtual environment holding the wheel, and commands run from a directory outside the checkout."""

    def __init__(self, directory: Path) -> None:
        self.venv = directory / "venv"
        self.home = directory / "elsewhere"
        self.home.mkdir()
        subprocess.run([sys.executable, "-m", "venv", str(self.venv)], check=True)
        self.env = {
            "PATH": f"{self.venv / 'bin'}:/usr/bin:/bin",
            "HOME": os.environ.get("HOME", str(directory)),
            "DATA_DIR": str(self.home / "data"),
        }

    def pip_install(self, requirement: str) -> None:
        command = [
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "-c",
            str(ROOT / "constraints.txt"),
        ]
        self.run(*command, requirement)

    def run(self, *command: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        program = str(self.venv / "bin" / command[0])
        done = subprocess.run(
            [program, *command[1:]], cwd=self.home, env=self.env, capture_output=True, text=True, check=False
        )
        if check:
            assert done.returncode == 0, (command, done.stdout[-3000:], done.stderr[-3000:])
        return done


@pytest.fixture(scope="module")
def install(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Install]:
    installed = Install(tmp_path_factory.mktemp("install"))
    installed.pip_install(str(wheel))
    yield installed


def test_the_engine_installs_without_the_server_and_passes_the_regression(install: Install) -> None:
    regress = install.run("navsim-lb", "regress")
    assert "no change against the golden results" in regress.stdout + regress.stderr  # rich prints to stderr
    probe = (
        "import importlib, pkgutil, sys, scorer\n"
        "for module in pkgutil.walk_packages(scorer.__path__, 'scorer.'):\n"
        "    importlib.import_module(module.name)\n"
        f"print(sorted(name for name in {NOT_ENGINE!r} if name in sys.modules))"
    )
    assert install.run("python", "-c", probe).stdout.strip() == "[]"
    serve = install.run("navsim-lb", "serve", "--port", "1", check=False)
    assert serve.returncode == 2
    assert SERVER_EXTRA in " ".join((serve.stdout + serve.stderr).split()), serve
    plot = install.run(
        "navsim-lb", "plot", "split", "submission.json", "token", "--out", "x.png", check=False
    )
    assert plot.returncode == 2
    assert PLOT_EXTRA in " ".join((plot.stdout + plot.stderr).split()), plot


def test_the_server_extra_migrates_and_serves_the_pages_from_the_wheel(install: Install, wheel: Path) -> None:
    install.pip_install(f"{wheel}[server]")
    install.run("navsim-lb", "db", "upgrade")
    head = head_revision()
    assert install.run("navsim-lb", "db", "current").stdout.split() == ["current:", head, "head:", head]
    port = free_port()
    command = [str(install.venv / "bin" / "navsim-lb"), "serve", "--host", "127.0.0.1", "--port", str(port)]
    base = f"http://127.0.0.1:{port}"
    with child_process(command, install.env, install.home / "serve.log"):
        wait_for(lambda: api_answers(base), "the installed server to answer")
        for path in ("/team", "/admin"):
            page = httpx.get(f"{base}{path}", timeout=10)
            assert page.status_code == 200, path
            assert "<title>" in page.text and "/static/style.css" in page.text, path
        # No split is registered yet: the leaderboard page says so, rendered from the installed templates.
        board = httpx.get(f"{base}/", timeout=10)
        assert board.status_code == 404 and "/static/style.css" in board.text
        for asset in (ROOT / "web" / "static").iterdir():
            served = httpx.get(f"{base}/static/{asset.name}", timeout=10)
            assert served.status_code == 200 and served.content == asset.read_bytes(), asset.name
        assert httpx.get(f"{base}/docs", timeout=10).status_code == 200
