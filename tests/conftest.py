"""Suite-wide settings: the shared fixture modules; property tests derandomised in CI (a red run reproduces)."""

from __future__ import annotations

import os

from hypothesis import settings

import scorer  # noqa: F401 - before the test modules load numpy: the official results' OpenBLAS kernels

# The shared fixtures, registered here (before any test module imports them) so their asserts are rewritten.
pytest_plugins = ["server_testing", "worker_testing"]

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
