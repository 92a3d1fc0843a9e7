"""The integrity checks (`server.services.integrity_checks`): the leaked-log threshold's calibration, and the
checks' time on a navtest-size split.

Calibration: how close honest entries come to the logged human future, against the threshold.
For the scenes of a split (the reference scenes by default) this prints, for each kind of entry, the median
and quantiles of the per-token average displacement (ADE) to the human's 8 future positions, over the tokens
where the human moves: the log itself (float32-rounded, as a NAVSIM pickle holds it), the log with a few
centimetres of noise, the demo's "noisy human" (0.3 m per coordinate) and constant velocity. The threshold must
sit well under every honest figure and above the copies'.

Speed: the three checks on random entries of a split of --tokens tokens (navtest: 12,146), --teams teams of
--uploads entries each (one seed), and reading the human futures from the scenes (per scene).
Usage: .venv/bin/python benchmarks/integrity.py [--split tests/fixtures/reference] [--tokens 12146]
       [--teams 20] [--uploads 5]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from scorer.baselines import constant_velocity, human
from scorer.human import human_future_poses
from scorer.scene import iter_scenes
from server.services.integrity_checks import (
    LEAK_MEDIAN_ADE_M,
    MOVING_M,
    Entry,
    displacements,
    leaked_log,
    near_duplicates,
    probing,
)


def calibration(split: Path) -> None:
    """Print each kind of entry's ADE to the human over the split's moving tokens."""
    scenes = list(iter_scenes(split))
    logged = np.stack([human(scene)[:, :2] for scene in scenes])
    path = np.linalg.norm(
        np.diff(np.concatenate([np.zeros((len(logged), 1, 2)), logged], axis=1), axis=1), axis=2
    )
    moving = path.sum(axis=1) >= MOVING_M
    rng = np.random.default_rng(0)
    entries = {
        "log, float32": logged.astype(np.float32).astype(np.float64),
        "log + 2 cm noise": logged + rng.normal(0.0, 0.02, logged.shape),
        "noisy human (demo, 0.3 m)": logged + rng.normal(0.0, 0.3, logged.shape),
        "constant velocity": np.stack([constant_velocity(scene)[:, :2] for scene in scenes]),
    }
    print(
        f"{len(scenes)} scenes, {moving.sum()} where the human moves >= {MOVING_M:g} m; threshold {LEAK_MEDIAN_ADE_M:g} m"
    )
    for name, positions in entries.items():
        ade = displacements(positions, logged).mean(axis=1)[moving]
        q05, q25, q50, q75 = np.quantile(ade, (0.05, 0.25, 0.5, 0.75))
        flagged = "flagged" if q50 < LEAK_MEDIAN_ADE_M else "not flagged"
        print(f"{name:28s} median ADE {q50:9.6f} m  (q05 {q05:.6f}, q25 {q25:.6f}, q75 {q75:.6f})  {flagged}")


def speed(split: Path, tokens: int, teams: int, uploads: int, seeds: int) -> None:
    """Print the CPU time of each check on random entries of `seeds` seeds (every seed is compared with every
    seed), and of reading the human futures per scene."""
    started = time.process_time()
    scenes = list(iter_scenes(split))
    for scene in scenes:
        human_future_poses(scene)
    per_scene = (time.process_time() - started) / len(scenes)
    rng = np.random.default_rng(0)
    names = [f"t{i}" for i in range(tokens)]
    human = np.cumsum(rng.uniform(0.0, 3.0, (tokens, 8, 2)), axis=1)
    entries = [
        Entry(
            team * uploads + upload,
            f"team {team}",
            f"{team}-{upload}",
            tuple(human + rng.normal(0.0, 0.5, human.shape) for _ in range(seeds)),
        )
        for team in range(teams)
        for upload in range(uploads)
    ]
    timings = {}
    started = time.process_time()
    for entry in entries:
        leaked_log(entry.submission_id, list(entry.seeds), human, names)
    timings["leaked log, per entry"] = (time.process_time() - started) / len(entries)
    started = time.process_time()
    near_duplicates(entries, names)
    timings[f"near-identical, {len(entries)} entries"] = time.process_time() - started
    started = time.process_time()
    for team in range(teams):
        probing(entries[team * uploads : (team + 1) * uploads], names)
    timings[f"probing, {teams} teams of {uploads}"] = time.process_time() - started
    print(f"reading the human future: {per_scene * 1e3:.1f} ms per scene (loading it included)")
    for name, seconds in timings.items():
        print(f"{name:32s} {seconds:8.3f} CPU-s on {tokens} tokens x {seeds} seeds")
    print(f"load average {os.getloadavg()[0]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", type=Path, default=Path("tests/fixtures/reference"))
    parser.add_argument("--tokens", type=int, default=12146)
    parser.add_argument("--teams", type=int, default=20)
    parser.add_argument("--uploads", type=int, default=5)
    parser.add_argument("--seeds", type=int, default=3)
    arguments = parser.parse_args()
    calibration(arguments.split)
    speed(arguments.split, arguments.tokens, arguments.teams, arguments.uploads, arguments.seeds)


if __name__ == "__main__":
    main()
