"""The server around the real engine: per-token results of `scorer.evaluate.score_tokens`, written through the
worker services, give leaderboard numbers equal to the official devkit's mean over the reference tokens."""

from __future__ import annotations

import gzip
import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
from server_testing import REFERENCE_DIR, REFERENCE_SUBMISSIONS, World, phase_row, team_row, upload_of

from scorer.evaluate import score_tokens
from server.db import transaction
from server.runs import claim_submission, mark_scored, write_chunk_results
from server.services.leaderboard import subscore_columns
from server.services.submissions import create_submission

FAMILY = "lane_change"


VERSIONS = ("v1.0", "v1.1", "v2.2")
# Where the official results of each version are (v2.2's: fixtures/epdms, README there).
EXPECTED = {"v1.0": REFERENCE_DIR / "expected", "v1.1": REFERENCE_DIR / "expected"} | {
    "v2.2": REFERENCE_DIR.parent / "epdms" / "expected"
}


def _official_mean(family: str, version: str, column: str) -> float:
    """Return the official mean of a column; an undefined value (v2.2's EC without a pair) is left out."""
    path = EXPECTED[version] / f"{family}.{version}.jsonl.gz"
    rows = [json.loads(line) for line in gzip.decompress(path.read_bytes()).splitlines()]
    defined = [row[column] for row in rows if row[column] is not None]
    return float(np.mean(defined)) if defined else math.nan


@pytest.mark.slow
def test_leaderboard_equals_the_devkit_mean_for_a_reference_family(world: World, tmp_path: Path) -> None:
    document = json.loads((REFERENCE_SUBMISSIONS / f"{FAMILY}.json").read_bytes())
    predictions = {
        token: np.asarray(poses, dtype=np.float64) for token, poses in document["predictions"].items()
    }
    with transaction(world.factory) as session:
        submission, _ = create_submission(
            session,
            team_row(session, world.team_id),
            phase_row(session, "test"),
            upload_of(b"lane change", method=FAMILY),
            world.settings.submission_store,
        )
        submission_id = submission.id
    with transaction(world.factory) as session:
        run = claim_submission(session, submission_id, "engine-test")
    for version in VERSIONS:
        started = time.perf_counter()
        results = score_tokens(REFERENCE_DIR, tmp_path / "cache", predictions, version)
        with transaction(world.factory) as session:
            assert write_chunk_results(
                session,
                submission_id,
                run,
                version,
                results,
                "engine-test",
                time.perf_counter() - started,
            )
    with transaction(world.factory) as session:
        assert mark_scored(session, submission_id, run, "engine", 200)
    for version in VERSIONS:
        row = world.client.get("/api/v1/leaderboard", params={"version": version}).json()["rows"][0]
        assert row["failed_tokens"] == 0
        # v2.2's official results come from another host (fixtures/epdms/README.md): EP within 1e-9.
        tolerance = 1e-9 if version == "v2.2" else 1e-12
        for column in ("score", *subscore_columns(version)):
            official = _official_mean(FAMILY, version, column)
            if math.isnan(official):  # EC where no two public scenes are adjacent frames: null on the board
                assert row[column] is None, (version, column)
                continue
            assert row[column] == pytest.approx(official, abs=tolerance), (version, column)
