"""The regression guard: versioned goldens exist for every metric version and `compare` catches changes."""

from __future__ import annotations

import pytest

from scorer.regression import TOLERANCE, _read_golden, compare
from scorer.regression.families import FAMILIES
from scorer.versions import VERSIONS


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
