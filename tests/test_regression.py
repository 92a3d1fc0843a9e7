"""The regression guard: versioned goldens exist for every metric version and `compare` catches changes."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from scorer.regression import (
    AGGREGATION,
    SPLIT_SEED,
    TOLERANCE,
    TWO_STAGE_GROUPS,
    TWO_STAGE_PAIRS,
    _read_golden,
    compare,
)
from scorer.regression.families import FAMILIES
from scorer.synth.two_stage import synthesize_two_stage_split
from scorer.two_stage.result_csv import SUMMARY_TOKENS
from scorer.versions import TWO_STAGE_VERSIONS, VERSIONS


@pytest.mark.parametrize("version", list(VERSIONS))
def test_goldens_cover_every_family_and_rank_the_human_first(version: str) -> None:
    golden = _read_golden(version)
    families = {family for family, _ in golden}
    assert families == set(FAMILIES)
    mean = {f: sum(float(r["score"]) for (g, _), r in golden.items() if g == f) / 24 for f in families}  # type: ignore[arg-type]
    assert max(mean, key=mean.__getitem__) == "human"
    assert mean["swerve_offroad"] < mean["constant_velocity"] < mean["human"]


def test_compare_reports_changes_above_the_tolerance_only() -> None:
    golden = _read_golden("v1.1")
    rows = [dict(row) for row in golden.values()]
    assert compare("v1.1", golden, rows) == []
    rows[0]["ego_progress"] = float(rows[0]["ego_progress"]) + TOLERANCE / 2  # type: ignore[arg-type]
    assert compare("v1.1", golden, rows) == []
    rows[1]["score"] = float(rows[1]["score"]) + 1e-6  # type: ignore[arg-type]
    rows[2]["valid"] = not rows[2]["valid"]
    dropped = rows.pop()
    changes = compare("v1.1", golden, rows)
    assert {(c[1], c[2], c[3]) for c in changes} == {
        (rows[1]["family"], rows[1]["token"], "score"),
        (rows[2]["family"], rows[2]["token"], "valid"),
        (dropped["family"], dropped["token"], "(row)"),
    }


AGGREGATION_GOLDEN = f"{TWO_STAGE_VERSIONS[0]}.{AGGREGATION}"


def test_the_two_stage_split_is_the_same_bytes_for_the_same_seed(tmp_path: Path) -> None:
    mappings = [synthesize_two_stage_split(tmp_path / name, 2, 2, SPLIT_SEED) for name in ("a", "b")]
    assert mappings[0] == mappings[1]
    files = [sorted((tmp_path / name).rglob("*.*")) for name in ("a", "b")]
    assert [path.relative_to(tmp_path / "a") for path in files[0]] == [
        path.relative_to(tmp_path / "b") for path in files[1]
    ]
    assert all(a.read_bytes() == b.read_bytes() for a, b in zip(*files, strict=True))
    [orig, prev, [[now2, prev2], _]] = mappings[0][0]
    assert (len(orig), len(prev), len(now2), len(prev2)) == (16, 16, 17, 17)


def test_the_two_stage_golden_covers_every_token_group_and_summary_row(tmp_path: Path) -> None:
    """Per family: every token of the two-stage regression split with its stage and weight (each stage-one
    frame's synthetic starts weighing 1 together), every group and the three summary rows; the human's
    combined score first."""
    mapping = synthesize_two_stage_split(tmp_path, TWO_STAGE_GROUPS, TWO_STAGE_PAIRS, SPLIT_SEED)
    golden = _read_golden(AGGREGATION_GOLDEN)
    tokens = {token: 1 for orig, prev, _ in mapping for token in (orig, prev)}
    tokens |= {token: 2 for _, _, pairs in mapping for pair in pairs for token in pair}
    expected = {*tokens, *(f"group {orig}" for orig, _, _ in mapping), *SUMMARY_TOKENS}
    assert golden.keys() == {(family, token) for family in FAMILIES for token in expected}
    for family in FAMILIES:
        assert all(golden[family, token]["stage"] == stage for token, stage in tokens.items())
        for _, _, pairs in mapping:
            for successors in zip(*pairs, strict=True):  # now2 tokens, then prev2 tokens
                weights = [float(golden[family, token]["weight"]) for token in successors]  # type: ignore[arg-type]
                assert math.isclose(sum(weights), 1.0, rel_tol=1e-12)
    combined = {family: golden[family, SUMMARY_TOKENS[2]]["score"] for family in FAMILIES}
    assert max(combined, key=combined.__getitem__) == "human"
    human_weights = {float(golden["human", token]["weight"]) for token, stage in tokens.items() if stage == 2}  # type: ignore[arg-type]
    assert len(human_weights) > 1  # the Gaussian weights, not only the uniform fallback


def test_compare_reports_a_changed_weight_group_value_or_summary_of_the_aggregation() -> None:
    golden = _read_golden(AGGREGATION_GOLDEN)
    rows = [dict(row) for row in golden.values()]
    assert compare(AGGREGATION_GOLDEN, golden, rows) == []
    weighted = next(row for row in rows if row.get("stage") == 2)
    group = next(row for row in rows if str(row["token"]).startswith("group "))
    summary = next(row for row in rows if row["token"] == SUMMARY_TOKENS[2])
    weighted["weight"] = float(weighted["weight"]) + 1e-6  # type: ignore[arg-type]
    group["combined.score"] = float(group["combined.score"]) + 1e-6  # type: ignore[arg-type]
    summary["official"] = not summary["official"]
    changes = compare(AGGREGATION_GOLDEN, golden, rows)
    assert {(c[1], c[2], c[3]) for c in changes} == {
        (weighted["family"], weighted["token"], "weight"),
        (group["family"], group["token"], "combined.score"),
        (summary["family"], summary["token"], "official"),
    }
