"""NAVSIM's split curation (paper, Section 3.2): drop near-trivial scenes and likely annotation errors.

A scene is dropped when the constant-velocity agent scores a PDMS above the threshold (0.8: the
scene needs no planning) or the recorded human scores below it (the labels are probably wrong).
The kept scene files are copied byte for byte, so their content hashes (and caches) stay valid.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from scorer.baselines import baseline_submission
from scorer.evaluate import TokenResult, score_tokens, summarize
from scorer.scene import scene_paths
from scorer.versions import DEFAULT_VERSION, VersionName

CURATION_THRESHOLD = 0.8
AGENTS = (("constant-velocity", "Constant velocity"), ("human", "Human"))
# Table 3 of the paper: the sub-metrics in its column order, then the score.
TABLE_COLUMNS = (
    ("NC", "no_at_fault_collisions"),
    ("DAC", "drivable_area_compliance"),
    ("TTC", "time_to_collision_within_bound"),
    ("C", "comfort"),
    ("EP", "ego_progress"),
    ("PDMS", "score"),
)
REPORT_NAME = "curation.json"


@dataclass(frozen=True)
class CurationResult:
    """Per-agent results over all tokens of the split, the kept tokens and why the others were dropped."""

    version: str
    threshold: float
    results: dict[str, list[TokenResult]]  # agent kind -> one result per token, split order
    kept: tuple[str, ...]
    dropped: dict[str, str]  # token -> reason


def curate_split(
    split_dir: Path,
    out_dir: Path,
    cache_dir: Path,
    version: VersionName = DEFAULT_VERSION,
    threshold: float = CURATION_THRESHOLD,
    progress: Callable[[int], None] | None = None,
) -> CurationResult:
    """Score both baselines on a split, copy the scenes that pass into `out_dir/scenes` and write curation.json."""
    paths = scene_paths(split_dir)
    out_scenes = out_dir / "scenes"
    if out_dir.resolve() == Path(split_dir).resolve():
        raise ValueError(f"{out_dir}: the curated split must be written to another directory")
    if out_scenes.is_dir() and any(out_scenes.iterdir()):
        raise ValueError(f"{out_scenes}: already holds scenes; choose an empty output directory")
    tokens = list(paths)
    results = {
        kind: score_tokens(
            split_dir,
            cache_dir,
            baseline_submission(split_dir, kind, name).seeds[0],
            version,
            tokens,
            None,
            progress,
        )
        for kind, name in AGENTS
    }
    dropped = _drop_reasons(results, threshold)
    kept = tuple(token for token in tokens if token not in dropped)
    out_scenes.mkdir(parents=True, exist_ok=True)
    for token in kept:
        shutil.copyfile(paths[token], out_scenes / paths[token].name)
    result = CurationResult(version, threshold, results, kept, dropped)
    report = {
        "format": "navsim-lb/curation",
        "version": 1,
        "source": str(split_dir),
        "metric_version": version,
        "threshold": threshold,
        "kept": list(kept),
        "dropped": dropped,
        "table": curation_table(result),
        "results": {kind: [asdict(r) for r in per_token] for kind, per_token in results.items()},
    }
    (out_dir / REPORT_NAME).write_text(json.dumps(report, indent=1) + "\n")
    return result


def _drop_reasons(results: dict[str, list[TokenResult]], threshold: float) -> dict[str, str]:
    reasons: dict[str, str] = {}
    for constant_velocity, human in zip(results["constant-velocity"], results["human"], strict=True):
        token = constant_velocity.token
        if not (constant_velocity.valid and human.valid):
            reasons[token] = f"not scorable: {constant_velocity.error or human.error}"
        elif constant_velocity.metrics["score"] > threshold:
            reasons[token] = (
                f"near-trivial: constant velocity scores {constant_velocity.metrics['score']:.4f} > {threshold}"
            )
        elif human.metrics["score"] < threshold:
            reasons[token] = (
                f"likely annotation error: human scores {human.metrics['score']:.4f} < {threshold}"
            )
    return reasons


def curation_table(result: CurationResult) -> list[list[str]]:
    """Return a header and one row per agent and split (all scenes, curated) in the layout of the paper's Table 3."""
    kept = set(result.kept)
    rows = [["Agent", "Scenes", "Tokens", *(name for name, _ in TABLE_COLUMNS)]]
    for kind, name in AGENTS:
        for label, selected in (
            ("all", result.results[kind]),
            ("curated", [r for r in result.results[kind] if r.token in kept]),
        ):
            summary = summarize(selected)
            rows.append(
                [
                    name,
                    label,
                    str(len(selected)),
                    *(f"{100 * summary[column]:.1f}" for _, column in TABLE_COLUMNS),
                ]
            )
    return rows
