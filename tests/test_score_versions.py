"""One simulation per token serves every metric version (`score_versions`), and one measurement the versions
that read the same inputs: each version's rows are the bits `score_tokens` gives it alone, a trajectory that
diverges fails in every version alone, and a scene one version cannot cache fails in that version only."""

from __future__ import annotations

import gzip
import json
import math
import shutil
from collections.abc import Collection
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from scorer import evaluate
from scorer.cache import MetricCache, _unpack, cache_path, load_caches
from scorer.evaluate import TokenResult, score_seeds, score_tokens, score_versions
from scorer.metrics.aggregation import aggregate
from scorer.pdm_scorer import RESULT_COLUMN_OF_ROW
from scorer.submission import load_submission
from scorer.versions import LOG_REPLAY_VERSIONS, VERSIONS, VersionName, cached_together

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
PROBES = Path(__file__).parent / "fixtures" / "epdms" / "probes"


def _same(ours: TokenResult, alone: TokenResult) -> bool:
    def bits(metrics: dict[str, float]) -> dict[str, str]:
        return {column: value.hex() for column, value in metrics.items()}

    return (ours.token, ours.seed, ours.valid, ours.error, ours.detail) == (
        alone.token,
        alone.seed,
        alone.valid,
        alone.error,
        alone.detail,
    ) and bits(ours.metrics) == bits(alone.metrics)


@pytest.mark.parametrize("family", ["swerve_offroad", "cv_decel"])
def test_every_versions_rows_are_those_it_gets_alone(family: str, tmp_path: Path) -> None:
    path = REFERENCE / "submissions" / f"{family}.json"
    poses = dict(load_submission(path.read_bytes(), path.name).seeds[0])
    diverging = sorted(poses)[3]
    poses[diverging] = np.full((8, 3), 1e200)  # finite, but the tracker's fit overflows
    with np.errstate(over="ignore", invalid="ignore"):
        together = score_versions(REFERENCE, tmp_path, poses, list(VERSIONS), seed=0)
        alone_rows = {
            version: score_tokens(REFERENCE, tmp_path, poses, version, seed=0) for version in VERSIONS
        }
    for version, alone in alone_rows.items():
        assert [row.token for row in together[version]] == [row.token for row in alone]
        assert all(_same(ours, theirs) for ours, theirs in zip(together[version], alone, strict=True))
        failed = {row.token: row.error or "" for row in together[version] if not row.valid}
        assert diverging in failed and all("scoring failed" in error for error in failed.values())
        # Reactive traffic also fails where the devkit cannot build its vehicles (2-vertex baselines here).
        others = {token for token in failed if token != diverging}
        if VERSIONS[version].reactive_traffic is None:
            assert not others
        assert all("reactive traffic" in failed[token] for token in others)


def test_every_seeds_rows_are_those_it_gets_alone(tmp_path: Path) -> None:
    """`score_seeds` reads a token's caches once and simulates every seed's trajectories together: each seed's
    rows are the bits `score_versions` gives it alone, v2.2's EC paired within the seed, and a trajectory that
    diverges fails in its seed only."""
    path = PROBES / "submissions" / "cv_decel.json"  # twins 0.5 s apart in one log: EC pairs them
    poses = dict(load_submission(path.read_bytes(), path.name).seeds[0])
    rng = np.random.default_rng(3)
    seeds: dict[int | None, dict[str, np.ndarray]] = {
        seed: {token: value + rng.normal(0.0, 0.3, value.shape) for token, value in poses.items()}
        for seed in range(3)
    }
    diverging = sorted(poses)[5]
    seeds[1][diverging] = np.full((8, 3), 1e200)
    with np.errstate(over="ignore", invalid="ignore"):
        together = score_seeds(PROBES, tmp_path, seeds, list(VERSIONS))
        for version in VERSIONS:
            alone = [
                row
                for seed, predictions in seeds.items()
                for row in score_versions(PROBES, tmp_path, predictions, [version], seed=seed)[version]
            ]
            assert [(row.token, row.seed) for row in together[version]] == [
                (row.token, row.seed) for row in alone
            ]
            assert all(_same(ours, theirs) for ours, theirs in zip(together[version], alone, strict=True))
            # Besides, reactive traffic fails where the devkit cannot build its vehicles (2-vertex baselines).
            failed = {
                (row.seed, row.token)
                for row in together[version]
                if not row.valid and "reactive traffic" not in (row.error or "")
            }
            assert failed == {(1, diverging)}
    ec = [row.metrics["two_frame_extended_comfort"] for row in together["v2.2"] if row.valid]
    assert any(not math.isnan(value) for value in ec)  # pairs were found within the seeds


def test_versions_that_observe_alike_are_measured_in_one_call(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every version holds the PDM-Closed centerline and route: one `measure_alike` call measures the three
    log-replay versions (v2.2's observation, without the tracks on the ego, and the settings apart, inside it);
    reactive traffic, whose observation depends on each trajectory, is measured in a call of its own."""
    path = REFERENCE / "submissions" / "cv_decel.json"
    poses = load_submission(path.read_bytes(), path.name).seeds[0]
    settings_per_call: list[int] = []
    measure_alike = evaluate.measure_alike

    def counted(*args: Any) -> Any:
        settings_per_call.append(len(args[-1]))
        return measure_alike(*args)

    monkeypatch.setattr(evaluate, "measure_alike", counted)
    # The first run builds the caches (their measures do not go through evaluate's name).
    score_versions(REFERENCE, tmp_path, poses, list(VERSIONS))
    settings_per_call.clear()
    score_versions(REFERENCE, tmp_path, poses, list(VERSIONS))
    assert settings_per_call == [1, 3]


def test_a_scene_one_version_cannot_cache_fails_in_that_version_only(tmp_path: Path) -> None:
    split = tmp_path / "split"
    shutil.copytree(REFERENCE / "scenes", split / "scenes")
    token = min(path.name.split(".")[0] for path in (split / "scenes").iterdir())
    scene_path = split / "scenes" / f"{token}.json.gz"
    raw = json.loads(gzip.decompress(scene_path.read_bytes()))
    raw["frames"] = raw["frames"][raw["current_index"] - 1 :]  # one past frame: v2.2 needs three
    raw["current_index"] = 1
    scene_path.write_bytes(gzip.compress(json.dumps(raw).encode()))
    poses = {token: np.arange(24, dtype=np.float64).reshape(8, 3) * [1.0, 0.0, 0.0]}
    rows = score_versions(split, tmp_path / "cache", poses, list(VERSIONS), [token])
    # v2.2, v2.2-prefix (v2.2's cache) and v2.2-two-stage need three past frames (history comfort).
    assert [rows[version][0].valid for version in VERSIONS] == [True, True, False, False, False]
    assert "could not be built" in (rows["v2.2"][0].error or "")
    assert rows["v2.2-prefix"][0].error == rows["v2.2"][0].error
    assert not math.isnan(rows["v1.1"][0].metrics["score"])


def test_caches_another_process_built_meanwhile_are_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two workers may miss a scene's cache at once: the one whose build finds the files written meanwhile
    (and so builds nothing) reads them instead of failing the token."""
    path = REFERENCE / "submissions" / "cv_decel.json"
    poses = load_submission(path.read_bytes(), path.name).seeds[0]
    token = min(poses)
    expected = score_versions(REFERENCE, tmp_path, poses, list(VERSIONS), [token])  # writes the caches
    missed: set[str] = set()

    def load_after_a_miss(
        cache_dir: Path, versions: Collection[str], name: str, scene_hash: str, data: bytes | None = None
    ) -> dict[str, MetricCache]:
        if name not in missed:  # the first look comes before the other process wrote the file
            missed.add(name)
            return {}
        return load_caches(cache_dir, versions, name, scene_hash, data)

    monkeypatch.setattr(evaluate, "load_caches", load_after_a_miss)
    rows = score_versions(REFERENCE, tmp_path, poses, list(VERSIONS), [token])
    assert missed == {token}
    for version in VERSIONS:
        assert _same(rows[version][0], expected[version][0])
        # Reactive traffic cannot be built on this scene's 2-vertex baselines, as in the devkit.
        assert rows[version][0].valid or "reactive traffic" in (rows[version][0].error or "")


def test_v2_2_prefix_reads_v2_2s_cache_and_is_off_the_board_by_default(tmp_path: Path) -> None:
    """v2.2-prefix's cache is v2.2's (NAVSIM's fix changed how a row's score is formed, nothing cached): scoring
    it builds the log-replay versions' caches and no section of its own, and the board's versions leave it out."""
    path = REFERENCE / "submissions" / "cv_decel.json"
    poses = load_submission(path.read_bytes(), path.name).seeds[0]
    token = min(poses)
    (row,) = score_tokens(REFERENCE, tmp_path, poses, "v2.2-prefix", [token])
    assert row.valid
    _, sections = _unpack(cache_path(tmp_path, token).read_bytes())
    assert set(sections) == {"v1.0", "v1.1", "v2.2"}
    assert cached_together(["v2.2-prefix"]) == list(LOG_REPLAY_VERSIONS) == ["v1.0", "v1.1", "v2.2"]
    assert not VERSIONS["v2.2-prefix"].published_by_default


def test_v2_row_scores_formed_at_once_are_the_bits_of_each_row_alone() -> None:
    version = VERSIONS[VersionName.V2_2]
    config = version.evaluation
    rng = np.random.default_rng(7)
    rows = []
    for index in range(600):
        row = {column: float(rng.choice([0.0, 0.5, 1.0])) for column in RESULT_COLUMN_OF_ROW.values()}
        row |= {column: float(rng.random()) for column in ("ego_progress", "time_to_collision_within_bound")}
        row["two_frame_extended_comfort"] = math.nan if index % 3 == 0 else float(rng.random())
        rows.append(row)

    def alone(row: dict[str, float]) -> float:
        # One row's (m, 1) and (w, 1) arrays, as the devkit's `compute_final_scores` forms a row's score.
        defined = not math.isnan(row["two_frame_extended_comfort"])
        multipliers = np.array([[row[RESULT_COLUMN_OF_ROW[name]]] for name in config.multiplier_rows])
        weighted = [row[RESULT_COLUMN_OF_ROW[name]] for name in config.weights]
        weighted.append(row["two_frame_extended_comfort"] if defined else 0.0)
        weights = [*config.weights.values(), version.two_frame_extended_comfort_weight if defined else 0.0]
        return float(aggregate(multipliers, np.array(weighted)[:, None], np.array(weights))[0])

    scores = evaluate.extended_scores(rows, version)
    assert [score.hex() for score in scores] == [alone(row).hex() for row in rows]
    assert len(set(scores)) > 100
