"""Suite-wide settings: the shared fixture modules; property tests derandomised in CI (a red run reproduces)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from hypothesis import settings

import scorer  # noqa: F401 - before the test modules load numpy: the official results' OpenBLAS kernels
from scorer.scene import scene_paths

# The shared fixtures, registered here (before any test module imports them) so their asserts are rewritten.
pytest_plugins = ["server_testing", "worker_testing"]

# pytest-xdist's workers start with COLUMNS=80 and LINES=24: rich's consoles, made once, would keep that
# width, and the tests that ask CliRunner for a wider terminal would not get it. A run is alike on one process.
for _variable in ("COLUMNS", "LINES"):
    os.environ.pop(_variable, None)

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.fixture
def one_token_split(tmp_path: Path) -> tuple[Path, Path]:
    """Return a split holding the first reference scene and a submission (JSON) predicting its token alone."""
    reference = Path(__file__).parent / "fixtures" / "reference"
    token, path = next(iter(scene_paths(reference).items()))
    (tmp_path / "split" / "scenes").mkdir(parents=True)
    (tmp_path / "split" / "scenes" / path.name).write_bytes(path.read_bytes())
    submission = json.loads((reference / "submissions" / "human_noise.json").read_text())
    submission["predictions"] = {token: submission["predictions"][token]}
    (tmp_path / "submission.json").write_text(json.dumps(submission))
    return tmp_path / "split", tmp_path / "submission.json"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Put the fault tests first: they wait (kills, outages, time limits) more than they compute, so on
    `make test`'s two processes they overlap the rest of the suite instead of following it."""
    waiting = ("test_worker_faults.py", "test_store_workers.py")
    items.sort(key=lambda item: item.path.name not in waiting)  # stable: the rest keep order
