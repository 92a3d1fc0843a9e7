"""The machine and software a benchmark ran on: the header of every benchmark's output, so that figures from
two hosts (a developer's laptop, CI, the server) are never compared unknowingly.

Call `host_header` in the main thread before any thread or process pool starts: threadpoolctl walks the
loaded libraries under the dynamic loader's lock and calls back into Python, so a thread loading an extension
module meanwhile deadlocks with it.
"""

from __future__ import annotations

# isort: off
from scorer import ENGINE_VERSION  # before numpy, so that numpy loads the official results' OpenBLAS kernels

# isort: on
import os
import platform
from pathlib import Path

import numpy
import scipy
import shapely
from threadpoolctl import threadpool_info

from scorer.blas import DEVKIT_KERNELS, KEEP_VARIABLE, blas_kernels, cpu_runs_devkit_kernels
from scorer.geometry import NUMPY_ARCTAN2_IS_SVML
from scorer.svml_tan import NUMPY_TAN_IS_SVML

# The environment variables that decide how many threads OpenBLAS runs, and which kernels.
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
KERNEL_VARIABLES = ("OPENBLAS_CORETYPE", KEEP_VARIABLE)


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """Return the CPU's model name as Linux lists it, or the platform's word for it elsewhere."""
    try:
        lines = cpuinfo.read_text().splitlines()
    except OSError:
        lines = []
    name = next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")), "")
    return name or platform.processor() or platform.machine() or "unknown CPU"


def openblas_libraries() -> list[tuple[str, str, int]]:
    """Return the package, version and thread count of each loaded OpenBLAS library."""
    return sorted(
        (
            Path(str(library.get("filepath", ""))).parent.name.removesuffix(".libs"),
            str(library.get("version") or "?"),
            int(library.get("num_threads") or 0),
        )
        for library in threadpool_info()
        if library.get("internal_api") == "openblas"
    )


def blas_threads() -> str:
    """Return each OpenBLAS library's threads, by the package that ships it, and the variables that set them."""
    libraries = [f"{package}'s {threads}" for package, _, threads in openblas_libraries()]
    variables = [
        f"{name}={os.environ[name]}" for name in THREAD_VARIABLES + KERNEL_VARIABLES if name in os.environ
    ]
    unset = [name for name in THREAD_VARIABLES if name not in os.environ]
    return "; ".join([", ".join(libraries) or "no OpenBLAS loaded", *variables, " ".join(unset) + " unset"])


def host_header() -> list[str]:
    """Return the lines that describe this host: CPU, cores, AVX-512, BLAS kernels and threads, versions."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    kernels = "+".join(blas_kernels()) or "none"
    official = (
        "the official results' kernels"
        if blas_kernels() == (DEVKIT_KERNELS,)
        else "not the official results'"
    )
    avx512 = "yes" if cpu_runs_devkit_kernels() else "no"
    # What numpy dispatches to (NPY_DISABLE_CPU_FEATURES can switch AVX-512 off on an AVX-512 CPU): where its
    # arctan2 and tan are not SVML's, the engine replays SVML's (docs/engine.md, "numpy's SVML functions").
    numpy_simd = (
        "SVML's arctan2 and tan"
        if NUMPY_ARCTAN2_IS_SVML and NUMPY_TAN_IS_SVML
        else "no SVML arctan2 and tan (the engine replays them)"
    )
    libraries = ", ".join(f"{package}'s {version}" for package, version, _ in openblas_libraries())
    software = (
        f"Python {platform.python_version()}, numpy {numpy.__version__}, scipy {scipy.__version__}, "
        f"shapely {shapely.__version__} (GEOS {shapely.geos_version_string}), engine {ENGINE_VERSION}"
    )
    rows = [
        ("CPU", f"{cpu_model()}, {os.cpu_count()} logical cores ({usable} usable by this process)"),
        ("AVX-512", f"{avx512} (what OpenBLAS's {DEVKIT_KERNELS} kernels need); numpy runs {numpy_simd}"),
        ("OpenBLAS", f"{kernels} ({official}): {libraries}"),
        ("BLAS threads", blas_threads()),
        ("software", software),
    ]
    width = max(len(key) for key, _ in rows)
    return ["host:"] + [f"  {key:<{width}}  {value}" for key, value in rows]
