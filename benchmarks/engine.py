"""Engine speed and memory: cache building and warm-cache scoring on a synthetic split.

Prints scenes per second of cache building (every version at once, as the CLI and the server build them,
and each version alone), tokens per second and CPU-ms per token of warm-cache scoring per version, for one
process and for all cores, the start-up cost of `navsim-lb score` (a one-token split, warm cache), and the
peak RSS.
Usage: .venv/bin/python benchmarks/engine.py [--scenes 1000] [--seed 1] [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from scorer.baselines import constant_velocity
from scorer.evaluate import build_split_cache, score_tokens
from scorer.scene import iter_scenes, scene_paths
from scorer.submission import Submission, SubmissionMetadata, dump_submission_json
from scorer.synth import synthesize_split
from scorer.versions import VERSIONS

DATA = Path(__file__).parent / ".data"


def _peak_rss_mib() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, children) / 1024


def _score_part(args: tuple[Path, Path, dict, str, list[str]]) -> int:
    split, cache_dir, predictions, version, tokens = args
    return sum(r.valid for r in score_tokens(split, cache_dir, predictions, version, tokens))


def _startup_seconds(split: Path, predictions: dict, cache_dir: Path, runs: int = 5) -> float:
    """Return the median wall time of `navsim-lb score` on a one-token split with a warm cache."""
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
    subprocess.run(command, check=True, capture_output=True)  # builds the one-token cache
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scenes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()

    split = DATA / f"split_{args.scenes}_{args.seed}"
    if not (split / "scenes").is_dir():
        start = time.perf_counter()
        synthesize_split(split, args.scenes, args.seed)
        print(f"synth: {args.scenes} scenes in {time.perf_counter() - start:.1f} s")
    predictions = {scene.token: constant_velocity(scene) for scene in iter_scenes(split)}
    tokens = sorted(predictions)
    print(f"split: {split} ({len(tokens)} tokens)")

    for workers in sorted({1, args.workers}):
        cache_dir = DATA / f"cache_{args.scenes}_{args.seed}_w{workers}"
        # Both versions at once, as `navsim-lb cache` and the server build them (one PDM-Closed unroll).
        shutil.rmtree(cache_dir, ignore_errors=True)
        start = time.perf_counter()
        failures = build_split_cache(split, cache_dir, list(VERSIONS), workers=workers)
        elapsed = time.perf_counter() - start
        print(
            f"cache all versions: {len(tokens) / elapsed:8.1f} scenes/s"
            f" ({len(VERSIONS) * len(tokens) / elapsed:.1f} scene-versions/s) with {workers} process(es)"
            f" ({elapsed:.1f} s, {len(failures)} failed)"
        )

    for version in VERSIONS:
        cache_dir = DATA / f"cache_{args.scenes}_{args.seed}_{version}"
        shutil.rmtree(cache_dir, ignore_errors=True)
        start, cpu_start = time.perf_counter(), time.process_time()
        build_split_cache(split, cache_dir, [version])
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu_start
        print(
            f"cache {version} alone: {len(tokens) / elapsed:8.1f} scenes/s with 1 process ({elapsed:.1f} s,"
            f" {1000 * cpu / len(tokens):.1f} CPU-ms per scene)"
        )
        shutil.rmtree(cache_dir)

    cache_dir = DATA / f"cache_{args.scenes}_{args.seed}_w1"
    for version in VERSIONS:
        start, cpu_start = time.perf_counter(), time.process_time()
        valid = sum(r.valid for r in score_tokens(split, cache_dir, predictions, version, tokens))
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu_start
        print(
            f"score {version}: {len(tokens) / elapsed:8.1f} tokens/s with 1 process"
            f" ({1000 * cpu / len(tokens):.2f} CPU-ms per token, {valid} valid)"
        )
        parts = [tokens[i :: args.workers] for i in range(args.workers)]
        start = time.perf_counter()
        with ProcessPoolExecutor(args.workers) as pool:
            valid = sum(
                pool.map(_score_part, [(split, cache_dir, predictions, version, part) for part in parts])
            )
        elapsed = time.perf_counter() - start
        print(
            f"score {version}: {len(tokens) / elapsed:8.1f} tokens/s with {args.workers} processes ({valid} valid)"
        )
    print(
        f"start-up: navsim-lb score of a one-token split takes {_startup_seconds(split, predictions, cache_dir):.2f} s"
        " (median of 5, warm cache)"
    )
    print(f"peak RSS: {_peak_rss_mib():.0f} MiB")


if __name__ == "__main__":
    main()
