"""Metric cache packs through the real service on an S3 store (moto, of the test's own): with chunks of whole
blocks, the worker that scores a first submission builds every cache and publishes each block's pack; a
second worker with an empty cache directory then scores a second submission reading each block's caches with
one GET of its pack (counted on the store's side, in moto's request log), builds nothing, and writes every row
once, the same as the rows of the first worker, which built its caches in its own directory."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
from object_stores import BUCKET, make_bucket
from own_s3 import own_s3
from sqlalchemy import select
from worker_testing import (
    SPLIT_SEED,
    Service,
    SplitFixture,
    predictions,
    running_service,
    wait_for,
    worker_command,
)

from navsim_lb.processes import STOP_TIMEOUT_S, child_process
from scorer.scene import scene_paths, scene_start
from scorer.submission import Submission as Predictions
from scorer.submission import SubmissionMetadata
from scorer.synth import synthesize_split
from scorer.versions import ALL_RESULT_COLUMNS, LOG_REPLAY_VERSIONS
from server.models import ScoringChunk, Status, TokenResultRow
from server.object_store import open_store
from server.runs import split_blocks
from server.runs._plan import PACK_TOKENS
from server.settings import get_settings
from server.shared_caches import _pack_key, engine_key, scene_hashes

PACKED_SCENES = 2 * PACK_TOKENS + 2  # blocks of 64, 64 and 2 tokens
# A request as moto's server logs it: method, path (bucket and key), status.
_REQUEST = re.compile(
    r'"(?:\x1b\[[0-9;]*m)*(GET|PUT|HEAD|POST) /([^ ?]+)\S* HTTP/1\.1(?:\x1b\[[0-9;]*m)*" (\d+)'
)


@pytest.fixture(scope="module")
def packed_split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A synthetic split of three blocks, no metric cache built."""
    directory = tmp_path_factory.mktemp("packed-split") / "split"
    synthesize_split(directory, PACKED_SCENES, SPLIT_SEED)
    return directory


def _requests(log: Path, prefix: str) -> list[tuple[str, str, int]]:
    """Return (method, key under `prefix`, status) of each request moto logged for a key under `prefix`."""
    matches = (_REQUEST.search(line) for line in log.read_text(errors="replace").splitlines())
    return [
        (match[1], match[2].removeprefix(prefix), int(match[3]))
        for match in matches
        if match and match[2].startswith(prefix)
    ]


def _rows(service: Service, submission_id: int) -> list[tuple[Any, ...]]:
    """Return every per-token row of a submission: its key (version, seed, token) and all it says."""
    fields = ("metric_version", "seed", "token", "valid", "error", "detail", *ALL_RESULT_COLUMNS)
    with service.factory() as session:
        rows = session.scalars(select(TokenResultRow).where(TokenResultRow.submission_id == submission_id))
        return [tuple(getattr(row, field) for field in fields) for row in rows]


def _contexts(service: Service, submission_id: int) -> set[str]:
    with service.factory() as session:
        query = select(ScoringChunk.context).where(ScoringChunk.submission_id == submission_id)
        return {token for context in session.scalars(query) for token in context}


def _scored(service: Service, submission_id: int) -> list[tuple[Any, ...]]:
    submission = service.final(submission_id)
    assert submission.status == Status.scored, (submission.status, submission.error, submission.error_detail)
    return _rows(service, submission_id)


def test_a_worker_with_an_empty_cache_reads_each_block_as_one_pack(
    tmp_path: Path, packed_split: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    hashes = scene_hashes(packed_split)
    starts = {token: scene_start(path) for token, path in scene_paths(packed_split).items()}
    blocks = split_blocks(starts)
    assert [len(block) for block in blocks] == [PACK_TOKENS, PACK_TOKENS, 2]
    packs = {_pack_key({token: hashes[token] for token in block}) for block in blocks}
    entry = predictions(packed_split, seeds=1, noise=0.3, method="builds the caches")
    # The same trajectories again (another file): its rows are the first's, whatever cache they came from.
    again = Predictions(SubmissionMetadata(method="reads the packs"), entry.seeds)
    first_cache, second_cache = tmp_path / "first-cache", tmp_path / "second-cache"
    with own_s3(tmp_path / "s3") as s3:
        monkeypatch.setenv("AWS_ENDPOINT_URL", s3.url)
        get_settings.cache_clear()
        make_bucket()
        cache_prefix = f"{BUCKET}/leaderboard/metric-cache/"
        settings = {
            "STORAGE_URL": f"s3://{BUCKET}/leaderboard",
            "AWS_ENDPOINT_URL": s3.url,
            "CHUNK_SIZE": str(PACK_TOKENS),  # one seed: chunks of one block each
        }
        root = tmp_path / "service"
        root.mkdir()
        split = SplitFixture(packed_split, first_cache)
        with running_service(
            root, split, settings | {"CACHE_DIR": str(first_cache)}, concurrency=1
        ) as service:
            first_rows = _scored(service, service.upload(entry))
            store = open_store(f"s3://{cache_prefix}")
            assert set(store.keys(f"{engine_key()}/packs/")) == packs
            assert {path.stem for path in first_cache.glob("*.nlc")} == set(hashes)  # built here
            service.worker.terminate()  # the second worker alone scores the second submission
            service.worker.wait(STOP_TIMEOUT_S)
            moto_log = tmp_path / "s3" / "moto.log"
            seen = len(_requests(moto_log, cache_prefix))
            second_env = service.env | {"CACHE_DIR": str(second_cache)}
            second_log = tmp_path / "second-worker.log"
            with child_process(worker_command(1, reaper=False, name="second"), second_env, second_log):
                wait_for(lambda: "ready." in second_log.read_text(errors="replace"), "the second worker")
                second_id = service.upload(again)
                second_rows = _scored(service, second_id)
            requests = _requests(moto_log, cache_prefix)[seen:]
            contexts = _contexts(service, second_id)
    # Every cache came from the store, each block's from its pack, read once and kept whole as one file.
    assert {path.relative_to(second_cache).as_posix() for path in second_cache.rglob("*.nlp")} == packs
    # The metric caches and their packs (not the human filter's futures, also kept there).
    engine = [(method, key, status) for method, key, status in requests if key.startswith(f"{engine_key()}/")]
    reads = [key for method, key, status in engine if method == "GET" and status == 200]
    assert sorted(key for key in reads if "/packs/" in key) == sorted(packs)
    # Only the comfort partners a chunk holds outside its block are read alone (when no pack brought them).
    read_alone = {
        key.removeprefix(f"{engine_key()}/").removesuffix(".nlc") for key in reads if "/packs/" not in key
    }
    assert read_alone <= {hashes[token] for token in contexts}
    assert {hashes[path.stem] for path in second_cache.glob("*.nlc")} == read_alone  # each kept as a file
    assert not [request for request in engine if request[0] != "GET" or request[2] != 200]  # none built
    assert (
        len(second_rows) == len({row[:3] for row in second_rows}) == PACKED_SCENES * len(LOG_REPLAY_VERSIONS)
    )
    assert sorted(second_rows, key=str) == sorted(first_rows, key=str)
