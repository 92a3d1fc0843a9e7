"""Metric-version regression guard: golden per-token results of a fixed synthetic split, v1.0, v1.1, v2.2.

The split is regenerated from its seed each run (the generator is deterministic), scored with every
trajectory family under every registered version, and compared with the versioned golden files.
"""

from __future__ import annotations

import json
import math
import tempfile
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

from scorer.evaluate import score_tokens
from scorer.regression.families import FAMILIES
from scorer.scene import iter_scenes
from scorer.versions import VERSIONS, get_version

GOLDEN_DIR = Path(__file__).parent / "golden"
SPLIT_SCENES = 24
SPLIT_SEED = 20261122
TOLERANCE = 1e-9

Change = tuple[str, str, str, str, object, object]


def compute_results(
    work_dir: Path, progress: Callable[[str, int], AbstractContextManager[Callable[[int], None]]]
) -> dict[str, list[dict[str, object]]]:
    """Return version -> rows (family, token, valid, metrics) of the regression split."""
    from scorer.synth import synthesize_split

    split = work_dir / "regression_split"
    synthesize_split(split, SPLIT_SCENES, SPLIT_SEED)
    scenes = list(iter_scenes(split))
    rows: dict[str, list[dict[str, object]]] = {version: [] for version in VERSIONS}
    with progress("regression split", len(VERSIONS) * len(FAMILIES) * len(scenes)) as advance:
        for version in VERSIONS:
            for family, make in FAMILIES.items():
                predictions = {scene.token: make(scene) for scene in scenes}
                for result in score_tokens(split, work_dir / "cache", predictions, version, progress=advance):
                    rows[version].append(
                        {"family": family, "token": result.token, "valid": result.valid, **result.metrics}
                    )
    return rows


def _golden_path(version: str) -> Path:
    # Plain JSON lines, one row per (family, token) in that order: a changed golden shows in a diff.
    return GOLDEN_DIR / f"{version}.jsonl"


def _read_golden(version: str) -> dict[tuple[str, str], dict[str, object]]:
    rows = [json.loads(line) for line in _golden_path(version).read_text().splitlines()]
    return {(row["family"], row["token"]): row for row in rows}


def compare(
    version: str, golden: dict[tuple[str, str], dict[str, object]], rows: list[dict[str, object]]
) -> list[Change]:
    """Return (version, family, token, metric, old, new) for every difference above the tolerance."""
    changes: list[Change] = []
    seen = set()
    for row in rows:
        key = (str(row["family"]), str(row["token"]))
        seen.add(key)
        old = golden.get(key)
        if old is None:
            changes.append((version, *key, "(row)", None, "new"))
            continue
        for metric in ("valid", *get_version(version).result_columns):
            before, after = old.get(metric), row.get(metric)
            if isinstance(before, float) and isinstance(after, float):
                if not (abs(before - after) <= TOLERANCE or math.isnan(before) and math.isnan(after)):
                    changes.append((version, *key, metric, before, after))
            elif before != after:
                changes.append((version, *key, metric, before, after))
    changes.extend((version, *key, "(row)", "present", None) for key in golden.keys() - seen)
    return changes


def run_regression(
    update: bool, progress: Callable[[str, int], AbstractContextManager[Callable[[int], None]]]
) -> list[Change]:
    """Score the regression split; rewrite the goldens when `update`, else return the changes."""
    with tempfile.TemporaryDirectory() as work_dir:
        results = compute_results(Path(work_dir), progress)
    changes: list[Change] = []
    for version, rows in results.items():
        if update:
            GOLDEN_DIR.mkdir(parents=True, exist_ok=True)
            ordered = sorted(rows, key=lambda row: (str(row["family"]), str(row["token"])))
            _golden_path(version).write_text(
                "".join(json.dumps(row, sort_keys=True) + "\n" for row in ordered)
            )
            continue
        if not _golden_path(version).exists():
            changes.append(
                (version, "-", "-", "(golden file)", "missing", "run `navsim-lb regress --update`")
            )
            continue
        changes.extend(compare(version, _read_golden(version), rows))
    return changes
