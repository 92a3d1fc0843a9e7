"""OpenBLAS kernels: the last bits of the official results depend on which ones run.

numpy's and SciPy's OpenBLAS choose their kernels when they load (by CPU, or as OPENBLAS_CORETYPE says),
and `pinv` (the tracker's velocity and curvature fits) rounds differently under each. The official
results were made with the SkylakeX kernels OpenBLAS picks on AVX-512 CPUs: under them the engine gives
every reference number bit for bit; under others (Haswell, say) ego progress and the score moved by up to
3e-13 on the reference scenes. So where the CPU can run them, importing `scorer` asks for the SkylakeX
kernels before numpy loads, whatever OPENBLAS_CORETYPE said (NAVSIM_LB_KEEP_OPENBLAS_CORETYPE=1 keeps
the environment's choice), and `kernel_warning` says when other kernels run, e.g. when numpy was loaded
before `scorer`.

The comfort filters call LAPACK in SciPy's OpenBLAS, as scipy does, through `scipy_lapack_function`: that
library alone, without importing `scipy.linalg` (docs/engine.md, "Start-up").
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from functools import cache
from pathlib import Path

from scorer import ENGINE_VERSION

DEVKIT_KERNELS = "SkylakeX"
KEEP_VARIABLE = "NAVSIM_LB_KEEP_OPENBLAS_CORETYPE"
# What OpenBLAS's SkylakeX kernels execute (AVX-512 foundation, byte/word, double/quad word, vector length).
_SKYLAKEX_CPU_FLAGS = frozenset({"avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl"})


def _cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> frozenset[str]:
    """Return the CPU's feature flags as Linux lists them; empty where there is no /proc/cpuinfo."""
    try:
        lines = cpuinfo.read_text().splitlines()
    except OSError:
        return frozenset()
    flags = next((line.split(":", 1)[1] for line in lines if line.startswith("flags")), "")
    return frozenset(flags.split())


def cpu_runs_devkit_kernels(cpu_flags: frozenset[str] | None = None) -> bool:
    """Whether this CPU (or one with `cpu_flags`) can run the devkit's OpenBLAS kernels (AVX-512)."""
    return _SKYLAKEX_CPU_FLAGS <= (_cpu_flags() if cpu_flags is None else cpu_flags)


def select_devkit_kernels(cpu_flags: frozenset[str] | None = None) -> None:
    """Ask OpenBLAS (when it loads later) for the devkit's kernels if this CPU can run them."""
    if os.environ.get(KEEP_VARIABLE):
        return
    if cpu_runs_devkit_kernels(cpu_flags):
        os.environ["OPENBLAS_CORETYPE"] = DEVKIT_KERNELS


_ONE_THREAD_PACKAGES = frozenset({"scipy"})  # whose OpenBLAS the engine loads with one thread


@cache  # the kernel check and the comfort filters both ask for SciPy's: finding it takes 0.2-0.5 ms
def _bundled_openblas(package: str, prefix: str) -> ctypes.CDLL | None:
    """Return the OpenBLAS a package's manylinux wheel bundles in `<package>.libs` as `<prefix><hash>.so`
    (auditwheel's layout), loaded without importing the package; None when there is not exactly one.

    Loaded by path, it is the very object the package's extensions link: the dynamic loader matches it by its
    soname, so the package shares it and it picks its kernels once, as `select_devkit_kernels` asked. The
    names are matched by hand: a glob pattern compiles regular expressions, milliseconds of every start-up.
    SciPy's loads with one thread (`_one_blas_thread`), numpy's as numpy would load it.
    """
    spec = importlib.util.find_spec(package)  # finds the package without importing it
    packages = spec.submodule_search_locations if spec is not None else None
    if not packages:
        return None
    libraries = Path(packages[0]).parent / f"{package}.libs"
    try:
        found = [name for name in os.listdir(libraries) if name.startswith(prefix) and name.endswith(".so")]
    except OSError:
        return None
    if len(found) != 1:
        return None
    with _one_blas_thread() if package in _ONE_THREAD_PACKAGES else nullcontext():
        return ctypes.CDLL(str(libraries / found[0]))


@contextmanager
def _one_blas_thread() -> Iterator[None]:
    """Have an OpenBLAS that loads meanwhile start one thread, whatever the environment asks.

    OpenBLAS reads OPENBLAS_NUM_THREADS once, when it loads, and starts that many threads, which the
    process joins when it exits: 15-25 ms of every `navsim-lb score` for SciPy's, whose only work in the
    engine is `dgelsd` on systems of at most 41 rows, too small for OpenBLAS to split between threads (so
    the bits are the same). numpy's OpenBLAS keeps the environment's choice.

    Only the main thread changes the environment: C's getenv is not synchronised with setenv, and a server's
    other threads may read it meanwhile (libpq does as it connects). A library loaded from another thread,
    an API thread drawing a picture, starts the threads the environment asks for; a server's exit time does
    not matter.
    """
    previous = os.environ.get("OPENBLAS_NUM_THREADS")
    if previous == "1" or threading.current_thread() is not threading.main_thread():
        yield
        return
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    try:
        yield
    finally:
        if previous is None:
            del os.environ["OPENBLAS_NUM_THREADS"]
        else:
            os.environ["OPENBLAS_NUM_THREADS"] = previous


@cache
def scipy_openblas() -> ctypes.CDLL:
    """Return SciPy's OpenBLAS, the library `scipy.linalg` calls, loaded without importing `scipy.linalg` (0.13 s
    of imports)."""
    library = _bundled_openblas("scipy", "libscipy_openblas")
    if library is None:
        raise ImportError(
            "SciPy's OpenBLAS: expected one libscipy_openblas*.so in scipy.libs; the engine calls the LAPACK of "
            "SciPy's Linux wheel from PyPI, as the devkit did (`pip install scipy`)"
        )
    return library


@cache
def scipy_lapack_function(name: str) -> Callable[..., None]:
    """Return LAPACK's routine `name` (e.g. "dgelsd") in SciPy's OpenBLAS, which prefixes its symbols with
    "scipy_" and, being Fortran, appends "_"; every argument goes by reference and nothing is returned."""
    function = getattr(scipy_openblas(), f"scipy_{name}_")
    function.restype = None
    return function


# The libraries the engine calls, each as its wheel bundles it, and its symbol naming OpenBLAS's kernels.
_KERNEL_SOURCES = (
    ("numpy", "libscipy_openblas64_", "scipy_openblas_get_corename64_"),
    ("scipy", "libscipy_openblas", "scipy_openblas_get_corename"),
)


@cache
def blas_kernels() -> tuple[str, ...]:
    """Return the kernel sets the OpenBLAS libraries the engine calls run (numpy's and SciPy's), "unknown"
    for one that is not a wheel's bundled OpenBLAS (another BLAS: the kernels cannot be the devkit's).

    Each library is asked by name (`openblas_get_corename`), in about a millisecond; loading it here, before
    numpy does, is harmless (`_bundled_openblas`). Forked processes inherit the cached answer.
    """
    kernels = set()
    for package, prefix, symbol in _KERNEL_SOURCES:
        library = _bundled_openblas(package, prefix)
        corename = getattr(library, symbol, None)
        if corename is None:
            kernels.add("unknown")
            continue
        corename.restype = ctypes.c_char_p
        kernels.add(corename().decode())
    return tuple(sorted(kernels))


def kernel_warning() -> str | None:
    """Return why results may differ from the devkit's in the last bits, or None under the devkit's kernels."""
    kernels = blas_kernels()
    if kernels == (DEVKIT_KERNELS,):
        return None
    forced = os.environ.get("OPENBLAS_CORETYPE")
    cause = f" (OPENBLAS_CORETYPE={forced})" if forced and forced != DEVKIT_KERNELS else ""
    remedy = (
        f"unset {KEEP_VARIABLE}"
        if os.environ.get(KEEP_VARIABLE)
        else f"import scorer before numpy on a CPU with AVX-512 ({', '.join(sorted(_SKYLAKEX_CPU_FLAGS))})"
    )
    return (
        f"OpenBLAS runs its {'+'.join(kernels)} kernels{cause}, not the {DEVKIT_KERNELS} ones of the official "
        f"results: ego progress and scores can differ from the devkit's in the last bits (up to 3e-13 on "
        f"the reference scenes). For bit-exact results, {remedy}."
    )


def engine_provenance() -> str:
    """Return what produced a number: the engine version and the OpenBLAS kernels it ran."""
    return f"{ENGINE_VERSION} OpenBLAS {'+'.join(blas_kernels())}"
