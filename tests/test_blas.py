"""`scorer.blas`: importing the engine selects the official results' OpenBLAS kernels where the CPU runs
them, says so when other kernels run, and the kernels are part of every result's and cache's provenance;
the engine calls SciPy's OpenBLAS without importing scipy."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from scorer import ENGINE_VERSION, blas
from scorer import cache as scorer_cache
from scorer.blas import (
    _SKYLAKEX_CPU_FLAGS,
    DEVKIT_KERNELS,
    KEEP_VARIABLE,
    _cpu_flags,
    engine_provenance,
    select_devkit_kernels,
)
from scorer.cache import build_caches, load_cache, save_caches
from scorer.scene import load_scene, scene_file_hash, scene_paths
from scorer.versions import VERSIONS

REFERENCE = Path(__file__).parent / "fixtures" / "reference"

AVX512_HOST = _SKYLAKEX_CPU_FLAGS <= _cpu_flags()
PROBE = """
import json, sys
if sys.argv[1] == "numpy-first":
    import numpy
import scorer
from scorer.blas import blas_kernels, kernel_warning
print(json.dumps({"kernels": blas_kernels(), "warning": kernel_warning()}))
"""


def _probe(order: str, **environment: str) -> dict[str, object]:
    """Return the kernels and warning of a fresh interpreter importing numpy and scorer in `order`."""
    env = {
        name: value for name, value in os.environ.items() if name not in ("OPENBLAS_CORETYPE", KEEP_VARIABLE)
    }
    done = subprocess.run(
        [sys.executable, "-c", PROBE, order],
        capture_output=True,
        text=True,
        check=False,
        env=env | environment,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_cpu_flags_are_read_from_cpuinfo(tmp_path: Path) -> None:
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f\nbugs\t\t: spectre\n")
    assert _cpu_flags(cpuinfo) == {"fpu", "sse2", "avx2", "avx512f"}
    assert _cpu_flags(tmp_path / "absent") == frozenset()


def test_selection_asks_for_skylakex_only_where_the_cpu_runs_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Haswell")
    monkeypatch.delenv(KEEP_VARIABLE, raising=False)
    select_devkit_kernels(frozenset({"avx2", "fma"}))
    assert os.environ["OPENBLAS_CORETYPE"] == "Haswell"
    select_devkit_kernels(_SKYLAKEX_CPU_FLAGS | {"avx2"})
    assert os.environ["OPENBLAS_CORETYPE"] == DEVKIT_KERNELS
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Haswell")
    monkeypatch.setenv(KEEP_VARIABLE, "1")
    select_devkit_kernels(_SKYLAKEX_CPU_FLAGS)
    assert os.environ["OPENBLAS_CORETYPE"] == "Haswell"


def test_importing_scorer_first_overrides_another_coretype() -> None:
    probed = _probe("scorer-first", OPENBLAS_CORETYPE="Haswell")
    if AVX512_HOST:
        assert probed == {"kernels": [DEVKIT_KERNELS], "warning": None}
    else:  # the devkit's kernels cannot run here: the other ones are used, and said so
        assert probed["kernels"] != [DEVKIT_KERNELS] and "kernels" in str(probed["warning"])


def test_other_kernels_are_kept_on_request_and_warned_about() -> None:
    probed = _probe("scorer-first", OPENBLAS_CORETYPE="Haswell", **{KEEP_VARIABLE: "1"})
    assert probed["kernels"] == ["Haswell"]
    assert "OpenBLAS runs its Haswell kernels (OPENBLAS_CORETYPE=Haswell)" in str(probed["warning"])
    assert f"unset {KEEP_VARIABLE}" in str(probed["warning"])


def test_numpy_loaded_before_scorer_is_warned_about() -> None:
    probed = _probe("numpy-first", OPENBLAS_CORETYPE="Haswell")
    assert "Haswell" in probed["kernels"]  # type: ignore[operator]
    assert "import scorer before numpy" in str(probed["warning"])


def test_provenance_names_the_engine_and_its_kernels() -> None:
    provenance = engine_provenance()
    kernels = provenance.removeprefix(f"{ENGINE_VERSION} OpenBLAS ")
    assert kernels != provenance and kernels
    if AVX512_HOST:
        assert kernels == DEVKIT_KERNELS


def test_a_cache_built_under_other_kernels_is_rebuilt(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = next(iter(scene_paths(REFERENCE).values()))
    scene = load_scene(path)
    cache = build_caches(scene, [VERSIONS["v1.1"]])["v1.1"]
    save_caches({"v1.1": cache}, tmp_path)
    assert load_cache(tmp_path, "v1.1", scene.token, scene_file_hash(path)) is not None
    other = "SkylakeX" if "Haswell" in scorer_cache.engine_provenance() else "Haswell"
    monkeypatch.setattr(scorer_cache, "engine_provenance", lambda: f"{ENGINE_VERSION} OpenBLAS {other}")
    assert load_cache(tmp_path, "v1.1", scene.token, scene_file_hash(path)) is None


KERNELS_BY_THREADPOOLCTL = """
import json
import scorer
import numpy
from scorer.blas import blas_kernels, scipy_openblas
scipy_openblas()
from threadpoolctl import threadpool_info
found = sorted({library["architecture"] for library in threadpool_info() if library["internal_api"] == "openblas"})
print(json.dumps({"asked": list(blas_kernels()), "found": found, "libraries": len(threadpool_info())}))
"""


@pytest.mark.parametrize("coretype", [DEVKIT_KERNELS, "Haswell", "Sandybridge"])
def test_the_kernels_asked_by_name_are_those_threadpoolctl_finds(coretype: str) -> None:
    """`blas_kernels` asks each bundled OpenBLAS for its core name instead of scanning every loaded library;
    threadpoolctl's scan must find the same kernels (and no third OpenBLAS)."""
    env = {**os.environ, "OPENBLAS_CORETYPE": coretype, KEEP_VARIABLE: "1"}
    done = subprocess.run(
        [sys.executable, "-c", KERNELS_BY_THREADPOOLCTL], env=env, capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr[-2000:]
    probed = json.loads(done.stdout)
    assert probed["asked"] == probed["found"] and probed["libraries"] == 2
    if coretype != DEVKIT_KERNELS or AVX512_HOST:
        assert probed["asked"] == [coretype]


def test_a_library_that_is_not_a_bundled_openblas_counts_as_unknown_kernels(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(blas, "_KERNEL_SOURCES", (("numpy", "libnothing", "openblas_get_corename"),))
    assert blas.blas_kernels.__wrapped__() == ("unknown",)


SHARED_LIBRARY = """
import json
import scorer
from scorer.blas import scipy_openblas
loaded = scipy_openblas()._name
import scipy.linalg
from threadpoolctl import threadpool_info
print(json.dumps({"loaded": loaded, "openblas": [library["filepath"] for library in threadpool_info()]}))
"""


def test_scipys_openblas_is_the_library_scipy_linalg_then_uses() -> None:
    """Loaded by path, SciPy's OpenBLAS is the very object its extensions link: no second copy, no second
    choice of kernels."""
    done = subprocess.run([sys.executable, "-c", SHARED_LIBRARY], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    probed = json.loads(done.stdout)
    scipys = [path for path in probed["openblas"] if "scipy.libs" in path]
    assert len(probed["openblas"]) == 2 and scipys == [probed["loaded"]]


THREADS = """
import json, os, sys, threading
import scorer
from scorer.blas import blas_kernels
if sys.argv[1] == "main":
    blas_kernels()  # loads both libraries, SciPy's first through the kernel check
else:
    loading = threading.Thread(target=blas_kernels)
    loading.start()
    loading.join()
import numpy
from threadpoolctl import threadpool_info
threads = {library["internal_api"] + ("-numpy" if "numpy.libs" in library["filepath"] else "-scipy"):
           library["num_threads"] for library in threadpool_info()}
print(json.dumps({"threads": threads, "variable": os.environ.get("OPENBLAS_NUM_THREADS")}))
"""
NUMPY_ALONE = """
import json, numpy
from threadpoolctl import threadpool_info
print(json.dumps([library["num_threads"] for library in threadpool_info()]))
"""


@pytest.mark.parametrize("variable", [None, "2"])
@pytest.mark.parametrize("thread", ["main", "other"])
def test_scipys_openblas_starts_one_thread_and_numpys_keeps_the_environments(
    variable: str | None, thread: str
) -> None:
    """SciPy's threads would only cost start-up and exit time (its systems are too small to split); numpy's
    OpenBLAS, and the environment a later library reads, are left as they were. Another thread than the main
    one never changes the environment (C's getenv is not synchronised with it): its SciPy takes the
    environment's threads."""
    environment = {key: value for key, value in os.environ.items() if key != "OPENBLAS_NUM_THREADS"}
    if variable is not None:
        environment["OPENBLAS_NUM_THREADS"] = variable
    probed, alone = (
        json.loads(
            subprocess.run(
                [sys.executable, "-c", *probe], capture_output=True, text=True, check=True, env=environment
            ).stdout
        )
        for probe in ((THREADS, thread), (NUMPY_ALONE,))
    )
    assert probed["variable"] == variable
    assert [probed["threads"]["openblas-scipy"]] == ([1] if thread == "main" else alone)
    assert [probed["threads"]["openblas-numpy"]] == alone
    if variable is not None:
        assert alone == [int(variable)]


SCORE_WITHOUT_SCIPY = """
import json, sys
from navsim_lb.cli import app
split, submission, cache = sys.argv[1:]
for version in ("v1.0", "v1.1", "v2.2"):
    try:
        app(["score", split, submission, "--version", version, "--cache-dir", cache])
    except SystemExit as done:
        assert not done.code, done.code
print("scipy modules:", json.dumps(sorted(name for name in sys.modules if name.split(".")[0] == "scipy")))
"""


def test_scoring_a_token_imports_no_scipy_module(tmp_path: Path, one_token_split: tuple[Path, Path]) -> None:
    """`navsim-lb score` starts without scipy (docs/engine.md, "Start-up"): the comfort filters reproduce
    ndimage's convolution in numpy and call dgelsd in SciPy's OpenBLAS directly. Caching and scoring every
    version of a token, as the command does on a fresh split, must not import a scipy module."""
    arguments = [*(str(path) for path in one_token_split), str(tmp_path / "cache")]
    done = subprocess.run(
        [sys.executable, "-c", SCORE_WITHOUT_SCIPY, *arguments], capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.splitlines()[-1] == "scipy modules: []"
