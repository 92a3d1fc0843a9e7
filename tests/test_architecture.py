"""The house's rules, read from the imports: routes only route, a run's internals stay in its package, and the
engine knows nothing of the server."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PRODUCT = ("scorer", "server", "worker", "navsim_lb", "web", "benchmarks")


def _imports(path: Path) -> set[str]:
    """Return every module `path` imports, at any depth (lazy imports inside functions too)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _modules(*directories: str) -> list[Path]:
    return sorted(path for directory in directories for path in (ROOT / directory).rglob("*.py"))


@pytest.mark.parametrize("path", _modules("server/routes"), ids=lambda path: path.name)
def test_a_route_module_imports_no_other_route_module(path: Path) -> None:
    assert not {name for name in _imports(path) if name.startswith("server.routes")}


@pytest.mark.parametrize(
    "path",
    [path for path in _modules(*PRODUCT) if not path.is_relative_to(ROOT / "server" / "runs")],
    ids=lambda path: str(path.relative_to(ROOT)),
)
def test_only_a_run_reaches_inside_a_run(path: Path) -> None:
    assert not {name for name in _imports(path) if name.startswith("server.runs._")}


def test_the_worker_is_glue_around_the_runs_face() -> None:
    """The worker's tasks reach the run's lifecycle through `server.runs` alone: no service, no query."""
    imported = _imports(ROOT / "worker" / "tasks.py")
    assert "server.runs" in imported
    services = {name for name in imported if name.startswith("server.services.")}
    assert services <= {"server.services.errors", "server.services.errors.NotFound"}
    queries = {
        name for name in imported if name.startswith("sqlalchemy") and not name.startswith("sqlalchemy.exc")
    }
    assert queries <= {"sqlalchemy.orm", "sqlalchemy.orm.Session", "sqlalchemy.orm.sessionmaker"}


@pytest.mark.parametrize("path", _modules("scorer"), ids=lambda path: str(path.relative_to(ROOT)))
def test_the_engine_imports_nothing_of_the_server(path: Path) -> None:
    assert not {name for name in _imports(path) if name.split(".")[0] in ("server", "worker", "navsim_lb")}
