"""Calibration of the leaked-log check (`server.services.integrity_checks`): how close honest entries come to
the logged human future, against the threshold.

For the scenes of a split (the reference scenes by default) this prints, for each kind of entry, the median
and quantiles of the per-token average displacement (ADE) to the human's 8 future positions, over the tokens
where the human moves: the log itself (float32-rounded, as a NAVSIM pickle holds it), the log with a few
centimetres of noise, the demo's "noisy human" (0.3 m per coordinate) and constant velocity. The threshold must
sit well under every honest figure and above the copies'.
Usage: .venv/bin/python benchmarks/integrity_calibration.py [--split tests/fixtures/reference]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from scorer.baselines import constant_velocity, human
from scorer.scene import iter_scenes
from server.services.integrity_checks import LEAK_MEDIAN_ADE_M, MOVING_M, displacements


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", type=Path, default=Path("tests/fixtures/reference"))
    arguments = parser.parse_args()
    scenes = list(iter_scenes(arguments.split))
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


if __name__ == "__main__":
    main()
