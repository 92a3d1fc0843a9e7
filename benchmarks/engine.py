"""Engine speed and memory per metric version: cache building and warm-cache scoring on a synthetic split.

Prints, under a header that describes the host (benchmarks/host.py):
- cache building, each in a fresh cache directory: every version alone, the two v1 versions together and all
  three together (as `navsim-lb cache` and the server build them: one PDM-Closed unroll serves them all),
  with 1 process and with --workers: scenes/s and CPU-ms per scene; then what the three versions' cache
  costs against the two v1 versions' on the same scenes (target: at most 1.5x);
- warm-cache scoring per version, with 1 process and with --workers: tokens/s and CPU-ms per token; then
  v2.2's cost per token against v1.1's (target: at most 2x);
- the reactive version (v2.2-two-stage: every token's IDM traffic simulated against its trajectory) per token
  against the official two-stage script's about 1 s per token in one process on the issue's machine
  (target: at least 100x, i.e. about 10 CPU-ms per token);
- within both, the floor: the CPU time of the SVDs the devkit's bits require (pinv's, two per simulated
  proposal: scorer/simulation.py), which no faster path may skip; the devkit's time divided by it bounds
  the speed-up any bit-identical engine can reach on this host;
- the ratio to that floor of each version alone and of the log-replay versions at once (the workers' call on a
  one-stage split: one simulation serves them all), ending with the two lines `floor ratio, scoring (all
  versions)` (target: at most 1.5x) and `floor ratio, cache (all versions)` (target: at most 2x); the reactive
  version is apart from those two, since its floor is its IDM traffic's, not the SVDs'; and the same call with
  three seeds (the workers score navtest entries with 3 seeds: what depends on the scene alone serves them all),
  per token and seed, `floor ratio, scoring (all versions, 3 seeds)`;
- apart from those, the start-up of `navsim-lb score` (a one-token split, warm cache) with and without
  `--out results.csv`, and of `navsim-lb --help`, against bare `python -c "import numpy, shapely"` (target: at
  most 1.5x in CPU time, the wall time beside it), each command run in turn with bare Python, pair by pair,
  and the ratio the median of the pairs' (on a shared host the speed drifts between two separate series of
  runs; within a pair much less), and peak RSS.
Every process runs one OpenBLAS thread (OPENBLAS_NUM_THREADS=1 unless set), as the workers do and as the
devkit is timed.
CPU time counts this process and its finished children (the process pool's), every thread of each. Cache
building and scoring are first run, untimed, on a few scenes, so that no row pays the first calls' costs.
Usage: .venv/bin/python benchmarks/engine.py [--scenes 1000] [--seed 1] [--workers 2]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads: one BLAS thread, as the workers run

import scorer  # noqa: F401 - before numpy: it selects the official results' OpenBLAS kernels

# isort: split

import argparse
import importlib
import resource
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Self, TypeVar

import numpy as np
from host import host_header

from scorer.baselines import constant_velocity, human
from scorer.evaluate import (
    build_missing_caches,
    build_split_cache,
    score_seeds,
    score_tokens,
)
from scorer.geometry import FloatArray
from scorer.scene import iter_scenes, scene_paths
from scorer.submission import Submission, SubmissionMetadata, dump_submission_json
from scorer.synth import synthesize_split
from scorer.versions import VERSIONS, VersionName

linalg_module = importlib.import_module("numpy.linalg._linalg")

DATA = Path(__file__).parent / ".data"
ALL_VERSIONS = tuple(VERSIONS)
V1_VERSIONS = (VersionName.V1_0, VersionName.V1_1)
CACHE_TARGET = 1.5  # the board's three versions' cache against the two v1 versions'
SCORE_TARGET = 2.0  # v2.2's scoring time per token against v1.1's
OFFICIAL_REACTIVE_SECONDS = 1.0  # the official two-stage script per token, one process (the target's anchor)
REACTIVE_TARGET = 100.0  # at least this many times the official script's speed per token
STARTUP_TARGET = 1.5  # a one-token `navsim-lb score` against bare Python importing numpy and shapely
STARTUP_PAIRS = 15
SCORE_FLOOR_TARGET = 1.5  # the log-replay versions at once per token and seed against their SVDs' CPU time
CACHE_FLOOR_TARGET = 2.0  # the log-replay versions' cache per scene against its SVDs' CPU time
# Every version whose floor is its SVDs: the reactive version's IDM traffic has a floor of its own.
LOG_REPLAY = tuple(name for name in ALL_VERSIONS if VERSIONS[name].reactive_traffic is None)
WARM_UP_SCENES = 4
T = TypeVar("T")


@dataclass(frozen=True)
class Timing:
    label: str
    processes: int
    count: int  # scenes or tokens
    seconds: float
    cpu_seconds: float  # this process and its finished children, all threads
    outcome: int  # failed scenes or valid tokens
    svd_cpu_seconds: float | None = None  # in this process (1-process runs only)

    def row(self) -> str:
        return (
            f"  {self.label:<26} {self.processes:>9} {self.count / self.seconds:>9.1f}"
            f" {1000 * self.cpu_seconds / self.count:>9.1f} {self.seconds:>8.2f} {self.outcome:>6}"
        )


def _label(versions: Sequence[str]) -> str:
    """Name a set of versions in a table row: the version alone, or which set it is."""
    if len(versions) == 1:
        return versions[0]
    if tuple(versions) == LOG_REPLAY:
        return "log-replay, at once"
    return "every version, at once" if tuple(versions) == ALL_VERSIONS else "+".join(versions)


def _cpu_seconds() -> float:
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def _timed(call: Callable[[], T]) -> tuple[T, float, float]:
    """Return what `call` returns, its wall seconds and its CPU seconds."""
    start, cpu_start = time.perf_counter(), _cpu_seconds()
    result = call()
    return result, time.perf_counter() - start, _cpu_seconds() - cpu_start


class SvdClock:
    """While active, count the CPU time numpy's SVD takes: pinv's, the call whose bits the devkit's results
    depend on (pinv looks `svd` up in its module, so wrapping that name catches every call)."""

    def __init__(self) -> None:
        self.cpu_seconds = 0.0

    def __enter__(self) -> Self:
        self._svd = linalg_module.svd

        def timed_svd(*args: object, **kwargs: object) -> object:
            start = time.process_time()
            try:
                return self._svd(*args, **kwargs)
            finally:
                self.cpu_seconds += time.process_time() - start

        linalg_module.svd = timed_svd
        return self

    def __exit__(self, *exc: object) -> None:
        linalg_module.svd = self._svd


def _floor(timing: Timing, svd_cpu_seconds: float, unit: str) -> str:
    """Say what share of `timing` the devkit's SVDs took, and which devkit time 100x would need."""
    floor_ms = 1000 * svd_cpu_seconds / timing.count
    share = svd_cpu_seconds / timing.cpu_seconds
    return (
        f"  {timing.label}: the SVDs pinv needs for the devkit's bits take {floor_ms:.2f} CPU-ms per {unit}"
        f" ({share:.0%} of the time): 100x the devkit here needs a devkit slower than {100 * floor_ms:.0f} ms"
        f" per {unit}, 50x one slower than {50 * floor_ms:.0f} ms; this run is {_floor_ratio(timing):.2f}x it"
    )


def _floor_ratio(timing: Timing) -> float:
    """Return `timing`'s CPU time against the CPU time of its SVDs (1-process runs only)."""
    return timing.cpu_seconds / (timing.svd_cpu_seconds or float("nan"))


def _floor_verdict(what: str, timing: Timing, target: float) -> str:
    ratio = _floor_ratio(timing)
    verdict = "within" if ratio <= target else "OVER"
    return f"  {what}: {ratio:.2f}x the floor ({verdict} the target of at most {target:g}x)"


def _header(unit: str, outcome: str) -> str:
    return f"  {'versions':<26} {'processes':>9} {unit + '/s':>9} {'CPU-ms':>9} {'seconds':>8} {outcome:>6}"


def _ratio(label: str, numerator: Timing, denominator: Timing, target: float) -> str:
    cpu = numerator.cpu_seconds / numerator.count / (denominator.cpu_seconds / denominator.count)
    wall = numerator.seconds / numerator.count / (denominator.seconds / denominator.count)
    verdict = "within" if cpu <= target else "OVER"
    return f"{label}: {cpu:.2f}x CPU, {wall:.2f}x wall ({verdict} the target of at most {target:g}x in CPU)"


def _against_official(timing: Timing) -> str:
    """Say how many times the official script's speed per token `timing` (reactive scoring) reaches."""
    cpu_ms = 1000 * timing.cpu_seconds / timing.count
    speed_up = 1000 * OFFICIAL_REACTIVE_SECONDS / cpu_ms
    verdict = "within" if speed_up >= REACTIVE_TARGET else "SHORT OF"
    return (
        f"{timing.label} per token, 1 process: {cpu_ms:.1f} CPU-ms, {speed_up:.0f}x the official script's"
        f" ~{OFFICIAL_REACTIVE_SECONDS:g} s ({verdict} the target of at least {REACTIVE_TARGET:g}x)"
    )


def _peak_rss_mib(who: int) -> float:
    return resource.getrusage(who).ru_maxrss / 1024


def _score_part(args: tuple[Path, Path, dict, str, list[str]]) -> int:
    split, cache_dir, predictions, version, tokens = args
    return sum(r.valid for r in score_tokens(split, cache_dir, predictions, version, tokens))


@dataclass(frozen=True)
class Startup:
    """A command's runs as a whole process, each paired with a run of bare Python right after it: the medians
    of the command's wall and CPU times (user + system; under load the wall time measures the host's other work
    too), of bare Python's, and of the pairs' ratios."""

    wall: float
    cpu: float
    bare_wall: float
    bare_cpu: float
    wall_ratio: float
    cpu_ratio: float

    def against_bare(self) -> str:
        verdict = "within" if self.cpu_ratio <= STARTUP_TARGET else "OVER"
        return (
            f"{self.wall:.3f} s, {self.wall_ratio:.2f}x bare Python; CPU {self.cpu:.3f} s, {self.cpu_ratio:.2f}x"
            f" ({verdict} {STARTUP_TARGET:g}x; bare Python in the same pairs {self.bare_wall:.3f} s,"
            f" CPU {self.bare_cpu:.3f} s)"
        )


def _run_timed(command: list[str]) -> tuple[float, float]:
    """Run `command` as a whole process; return its wall and CPU seconds."""
    before, start = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
    subprocess.run(command, check=True, capture_output=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime


def _paired_startup(command: list[str], pairs: int = STARTUP_PAIRS) -> Startup:
    """Time `command` and bare Python in turn, `pairs` times each, after one untimed run of both (the file
    system's caches)."""
    bare = [sys.executable, "-c", "import numpy, shapely"]
    subprocess.run(command, check=True, capture_output=True)
    subprocess.run(bare, check=True, capture_output=True)
    runs = [(_run_timed(command), _run_timed(bare)) for _ in range(pairs)]
    median = statistics.median
    return Startup(
        wall=median(own[0] for own, _ in runs),
        cpu=median(own[1] for own, _ in runs),
        bare_wall=median(other[0] for _, other in runs),
        bare_cpu=median(other[1] for _, other in runs),
        wall_ratio=median(own[0] / other[0] for own, other in runs),
        cpu_ratio=median(own[1] / other[1] for own, other in runs),
    )


def _startup(split: Path, predictions: dict, out: bool) -> Startup:
    """Return the medians of `navsim-lb score` on a one-token split with a warm cache, writing the
    results CSV where `out` is set."""
    token, path = next(iter(scene_paths(split).items()))
    one = DATA / "split_one"
    shutil.rmtree(one, ignore_errors=True)
    (one / "scenes").mkdir(parents=True)
    shutil.copy(path, one / "scenes" / path.name)
    submission = DATA / "one_token.json"
    submission.write_bytes(
        dump_submission_json(Submission(SubmissionMetadata(method="cv"), ({token: predictions[token]},)))
    )
    command = [str(Path(sys.executable).with_name("navsim-lb")), "score", str(one), str(submission)]
    command += ["--cache-dir", str(DATA / "cache_one")]
    command += ["--out", str(DATA / "one_token.csv")] if out else []
    return _paired_startup(command)  # its first, untimed run builds the one-token cache


def build_cache(split: Path, cache_dir: Path, versions: Sequence[str], workers: int, count: int) -> Timing:
    """Build the split's cache of `versions` in the fresh directory `cache_dir`; return how long it took."""
    shutil.rmtree(cache_dir, ignore_errors=True)
    with SvdClock() as svd:
        failures, seconds, cpu = _timed(
            lambda: build_split_cache(split, cache_dir, versions, workers=workers)
        )
    svd_cpu = svd.cpu_seconds if workers == 1 else None
    return Timing(_label(versions), workers, count, seconds, cpu, len(failures), svd_cpu)


def score(
    split: Path, cache_dir: Path, predictions: dict, version: str, tokens: list[str], workers: int
) -> Timing:
    """Score every token under `version` with `workers` processes on a warm cache; return how long it took."""
    if workers == 1:
        with SvdClock() as svd:
            valid, seconds, cpu = _timed(
                lambda: sum(r.valid for r in score_tokens(split, cache_dir, predictions, version, tokens))
            )
        return Timing(version, workers, len(tokens), seconds, cpu, valid, svd.cpu_seconds)
    parts = [(split, cache_dir, predictions, version, tokens[i::workers]) for i in range(workers)]

    def in_pool() -> int:
        with ProcessPoolExecutor(workers) as pool:
            return sum(pool.map(_score_part, parts))

    valid, seconds, cpu = _timed(in_pool)
    return Timing(version, workers, len(tokens), seconds, cpu, valid)


def three_seeds(split: Path, predictions: dict[str, FloatArray]) -> dict[int | None, dict[str, FloatArray]]:
    """Return three seeds' predictions that differ as seeds do: constant velocity, the human's poses, and
    constant velocity slowed to 90 %."""
    slower = {
        token: poses * np.array([0.9, 0.9, 1.0], dtype=poses.dtype) for token, poses in predictions.items()
    }
    return {0: predictions, 1: {scene.token: human(scene) for scene in iter_scenes(split)}, 2: slower}


def score_at_once(
    split: Path, cache_dir: Path, seeds: dict[int | None, dict[str, FloatArray]], tokens: list[str]
) -> Timing:
    """Score every token and seed under every log-replay version at once (the workers' call), one process."""
    with SvdClock() as svd:
        valid, seconds, cpu = _timed(
            lambda: sum(
                row.valid
                for rows in score_seeds(split, cache_dir, seeds, LOG_REPLAY, tokens).values()
                for row in rows
            )
        )
    label = _label(LOG_REPLAY) if len(seeds) == 1 else f"log-replay, {len(seeds)} seeds"
    return Timing(label, 1, len(tokens) * len(seeds), seconds, cpu, valid, svd.cpu_seconds)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scenes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    print("\n".join(host_header()), flush=True)  # before any process pool (host.py says why)

    split = DATA / f"split_{args.scenes}_{args.seed}"
    if not (split / "scenes").is_dir():
        start = time.perf_counter()
        synthesize_split(split, args.scenes, args.seed)
        print(f"synth: {args.scenes} scenes in {time.perf_counter() - start:.1f} s")
    predictions = {scene.token: constant_velocity(scene) for scene in iter_scenes(split)}
    tokens = sorted(predictions)
    print(f"split: {split} ({len(tokens)} tokens)")
    process_counts = sorted({1, args.workers})
    stem = DATA / f"cache_{args.scenes}_{args.seed}"

    warm_up = DATA / "cache_warm_up"
    shutil.rmtree(warm_up, ignore_errors=True)
    build_missing_caches(list(scene_paths(split).values())[:WARM_UP_SCENES], warm_up, ALL_VERSIONS)
    shutil.rmtree(warm_up)

    print("\ncache building, each in a fresh cache directory (CPU-ms per scene):")
    print(_header("scenes", "failed"), flush=True)
    alone: list[Timing] = []
    for version in ALL_VERSIONS:
        alone.append(build_cache(split, Path(f"{stem}_{version}"), [version], 1, len(tokens)))
        print(alone[-1].row(), flush=True)
        shutil.rmtree(f"{stem}_{version}")
    v1 = build_cache(split, Path(f"{stem}_v1"), V1_VERSIONS, 1, len(tokens))
    print(v1.row(), flush=True)
    shutil.rmtree(f"{stem}_v1")
    # What the workers build: the log-replay versions (the reactive one's cache is built only where asked for).
    board = build_cache(split, Path(f"{stem}_board"), LOG_REPLAY, 1, len(tokens))
    print(board.row(), flush=True)
    shutil.rmtree(f"{stem}_board")
    cache_dir = Path(f"{stem}_w1")  # all versions, 1 process: the cache the scoring below reads
    every = build_cache(split, cache_dir, ALL_VERSIONS, 1, len(tokens))
    print(every.row(), flush=True)
    for workers in process_counts[1:]:
        print(build_cache(split, Path(f"{stem}_w{workers}"), ALL_VERSIONS, workers, len(tokens)).row())
        shutil.rmtree(f"{stem}_w{workers}")
    print(_ratio("the log-replay versions against the two v1 versions, 1 process", board, v1, CACHE_TARGET))
    print("the floor of cache building, 1 process:")
    for timing in (*alone, board):
        print(_floor(timing, timing.svd_cpu_seconds or 0.0, "scene"))
    print(_floor_verdict("the log-replay versions' cache at once", board, CACHE_FLOOR_TARGET))

    for version in ALL_VERSIONS:
        score_tokens(split, cache_dir, predictions, version, tokens[:WARM_UP_SCENES])
    print("\nwarm-cache scoring (CPU-ms per token):")
    print(_header("tokens", "valid"), flush=True)
    single: dict[str, Timing] = {}
    for version in ALL_VERSIONS:
        for workers in process_counts:
            timing = score(split, cache_dir, predictions, version, tokens, workers)
            single.setdefault(version, timing)
            print(timing.row(), flush=True)
    # The workers' call: every log-replay version of a token from one simulation, with one seed and with three.
    at_once = score_at_once(split, cache_dir, {None: predictions}, tokens)
    print(at_once.row(), flush=True)
    seeded = score_at_once(split, cache_dir, three_seeds(split, predictions), tokens)
    print(seeded.row(), flush=True)
    v2_2, v1_1 = single[VersionName.V2_2], single[VersionName.V1_1]
    print(_ratio("v2.2 against v1.1 per token, 1 process", v2_2, v1_1, SCORE_TARGET))
    print(_against_official(single[VersionName.V2_2_TWO_STAGE]))
    print("the floor of scoring, 1 process:")
    for timing in (*single.values(), at_once):
        print(_floor(timing, timing.svd_cpu_seconds or 0.0, "token"))
    print(_floor(seeded, seeded.svd_cpu_seconds or 0.0, "token and seed"))
    print(_floor_verdict("the log-replay versions at once, per token and seed", at_once, SCORE_FLOOR_TARGET))

    print(
        f"\nstart-up, each run paired with one of bare Python (python -c 'import numpy, shapely'), {STARTUP_PAIRS}"
        " pairs, medians:"
    )
    navsim_lb = str(Path(sys.executable).with_name("navsim-lb"))
    for label, startup in (
        ("navsim-lb score of a one-token split (warm cache)", _startup(split, predictions, out=False)),
        ("the same with --out results.csv", _startup(split, predictions, out=True)),
        ("navsim-lb --help", _paired_startup([navsim_lb, "--help"])),
    ):
        print(f"  {label}: {startup.against_bare()}")
    print(
        f"peak RSS: {_peak_rss_mib(resource.RUSAGE_SELF):.0f} MiB this process,"
        f" {_peak_rss_mib(resource.RUSAGE_CHILDREN):.0f} MiB its largest child (a pool process or navsim-lb)"
    )
    print(f"floor ratio, scoring (all versions): {_floor_ratio(at_once):.2f}x")
    print(f"floor ratio, scoring (all versions, 3 seeds): {_floor_ratio(seeded):.2f}x")
    print(f"floor ratio, cache (all versions): {_floor_ratio(board):.2f}x")


if __name__ == "__main__":
    main()
