"""Workers that share no filesystem with the API or each other, reaching everything through the network: the
split's scenes, the uploads and the metric caches in an S3 store (moto, on ports of the test's own), the queue
and the rows in Redis and PostgreSQL. And the store down for twenty seconds while chunks run: the chunks wait
and go on, nothing is lost or doubled, uploads are refused with a 503 saying so, the board is still served.

Each worker runs in a network namespace of its own (tests/netns.py: skipped, saying so, only where the
machine refuses `ip netns add`), reaching PostgreSQL, Redis and the store of the test's own on the host side
of a veth pair, with a data directory of its own."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from netns import namespaces
from object_stores import BUCKET, make_bucket
from own_s3 import Gate, own_s3
from own_servers import own_postgres, own_redis
from sqlalchemy import func, select
from worker_testing import (
    Service,
    SplitFixture,
    assert_scored_once,
    predictions,
    running_service,
    wait_for,
    worker_command,
)

from navsim_lb.processes import child_process
from scorer.scene import scene_paths
from scorer.submission import dump_submission_json
from scorer.versions import LOG_REPLAY_VERSIONS as VERSIONS
from server.main import STORE_DOWN
from server.models import ChunkState, ScoringChunk, Summary
from server.object_store import open_store
from server.settings import get_settings
from server.shared_caches import publish_caches, scene_hashes

REDIS_URL = os.environ.get("NAVSIM_LB_TEST_REDIS", "redis://127.0.0.1:6379/0")
OUTAGE_S = 20.0
RECOVERY_S = 120.0


def _stored_split(
    s3: Gate, split: SplitFixture, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> tuple[str, str]:
    """Put the split's scenes and its metric caches in the store; return the split's and the storage's URLs.
    The test process registers the split as an organiser's machine would, with a data directory of its own."""
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3.url)
    monkeypatch.setenv("DATA_DIR", str(tmp_path / "organiser"))
    get_settings.cache_clear()
    make_bucket()
    split_url, storage_url = f"s3://{BUCKET}/split", f"s3://{BUCKET}/leaderboard"
    scenes = open_store(f"{split_url}/scenes")
    for path in scene_paths(split.directory).values():
        scenes.put_bytes(path.name, path.read_bytes())
    # Built once by an earlier worker: these workers read them instead of building.
    publish_caches(open_store(f"{storage_url}/metric-cache"), split.cache_dir, scene_hashes(split.directory))
    return split_url, storage_url


def _chunks(service: Service, submission_id: int) -> list[ScoringChunk]:
    with service.factory() as session:
        return list(session.scalars(select(ScoringChunk).where(ScoringChunk.submission_id == submission_id)))


def _scenes_on_disk(data_dir: Path) -> set[str]:
    return {path.name for path in data_dir.glob("split-cache/*/scenes/*")}


@pytest.mark.services
def test_two_workers_sharing_no_disk_score_every_row_once(
    tmp_path: Path, synthetic_split: SplitFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    with namespaces(2) as (first_net, second_net):
        servers = first_net.host  # every server listens there (and on loopback): each namespace routes to it
        with (
            own_s3(tmp_path / "s3", servers) as s3,
            own_postgres(servers) as database,
            own_redis(tmp_path / "redis", servers) as broker,
        ):
            split_url, storage_url = _stored_split(s3, synthetic_split, monkeypatch, tmp_path)
            network = {"DATABASE_URL": database.url, "BROKER_URL": broker.url, "QUEUE_NAME": "store-workers"}
            shared = network | {"STORAGE_URL": storage_url, "AWS_ENDPOINT_URL": s3.url, "CHUNK_SIZE": "2"}
            api_dir, second_dir = tmp_path / "api-and-first-worker", tmp_path / "second-worker"
            api_dir.mkdir()
            second_dir.mkdir()
            own = {"CACHE_DIR": str(api_dir / "cache")}
            with running_service(
                api_dir,
                synthetic_split,
                shared | own,
                concurrency=1,
                split_location=split_url,
                worker_prefix=first_net.command([]),
            ) as service:
                second_env = service.env | {
                    "DATA_DIR": str(second_dir),
                    "CACHE_DIR": str(second_dir / "cache"),
                }
                second_command = second_net.command(worker_command(1, reaper=False, name="second"))
                with child_process(second_command, second_env, second_dir / "worker.log") as second_worker:
                    wait_for(
                        lambda: "ready." in (second_dir / "worker.log").read_text(errors="replace"),
                        "worker 2",
                    )
                    entry = predictions(
                        synthetic_split.directory, seeds=2, noise=0.3, method="no shared disk"
                    )
                    submission_id = service.upload(entry)
                    service.final(submission_id)
                    assert_scored_once(service, synthetic_split, submission_id, entry)
                    chunks = _chunks(service, submission_id)
                    workers = {chunk.worker.split("/")[0] for chunk in chunks if chunk.worker}
                    # Each worker in a network namespace of its own: it sees its veth and loopback only.
                    spaces = {_network_namespace(pid) for pid in (service.worker.pid, second_worker.pid)}
                    assert len(spaces) == 2 and _network_namespace(os.getpid()) not in spaces
    assert len(workers) == 2  # both scored
    assert not (api_dir / "submissions").exists() and not (second_dir / "submissions").exists()
    # Each read the caches of the tokens it scored from the store, and so fetched no scene.
    cached = [
        {path.name.removesuffix(".nlc") for path in (data / "cache").iterdir()}
        for data in (api_dir, second_dir)
    ]
    assert all(cached) and set.union(*cached) == set(scene_paths(synthetic_split.directory))
    assert not _scenes_on_disk(api_dir) and not _scenes_on_disk(second_dir)


def _network_namespace(pid: int) -> str:
    return os.readlink(f"/proc/{pid}/ns/net")


def test_the_store_down_for_twenty_seconds_while_chunks_run(
    tmp_path: Path, synthetic_split: SplitFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    faults = {"FAULT_CHUNK_SECONDS": "2", "CHUNK_SIZE": "4", "REAPER_INTERVAL": "5"}
    with own_s3(tmp_path / "s3") as s3:
        split_url, storage_url = _stored_split(s3, synthetic_split, monkeypatch, tmp_path)
        settings = {
            "STORAGE_URL": storage_url,
            "AWS_ENDPOINT_URL": s3.url,
            "CACHE_DIR": str(tmp_path / "cache"),
        }
        root = tmp_path / "service"
        root.mkdir()
        with running_service(
            root, synthetic_split, settings | faults, faults=True, split_location=split_url
        ) as service:
            entry = predictions(synthetic_split.directory, seeds=1, noise=0.3, method="store outage")
            submission_id = service.upload(entry)
            wait_for(
                lambda: any(c.state == ChunkState.running for c in _chunks(service, submission_id)),
                "a chunk to run",
            )
            s3.close()
            closed = time.monotonic()
            late = dump_submission_json(
                predictions(synthetic_split.directory, seeds=1, noise=0.5, method="late")
            )
            with service.client() as client:
                while time.monotonic() - closed < OUTAGE_S:
                    refused = client.post("/api/v1/submissions", files={"file": ("late.json", late)})
                    assert refused.status_code == 503 and refused.json() == {"detail": STORE_DOWN}, (
                        refused.text
                    )
                    board = client.get("/api/v1/leaderboard", params={"phase": "test"})
                    assert board.status_code == 200, board.text
                    time.sleep(2)
            s3.open()
            service.final(submission_id, timeout=RECOVERY_S)
            assert_scored_once(service, synthetic_split, submission_id, entry)
            assert "object store unreachable" in service.worker_log()  # the chunks waited, and went on
            with service.factory() as session:
                assert session.scalar(select(func.count()).select_from(Summary)) == len(
                    VERSIONS
                )  # no late row
