"""Splits registered from an object store (CI's moto server): the same tokens and content hash as from a
directory; other machines read the manifest, not the scenes; a worker fetches only the scenes it needs, each
checked, within a bounded mirror; a missing or changed scene is an error naming the object. Metric caches
built by one worker are published once and read by the others."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import os
import shutil
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import boto3
import numpy as np
import pytest
import typer
from object_stores import fresh_s3_store
from server_testing import REFERENCE_DIR, World
from sqlalchemy import select
from two_stage_reference import EXCERPT, EXCERPT_STAGES, family_poses, family_submission
from typer.testing import CliRunner
from worker_testing import SplitFixture

from scorer.cache import cache_path
from scorer.evaluate import split_content_hash
from scorer.explain import explain_split_token
from scorer.scene import scene_paths
from scorer.submission import dump_two_stage_submission_json
from scorer.two_stage.split import MAPPING_FILE
from server import split_store
from server.cli import register
from server.db import make_engine, make_session_factory, transaction
from server.models import Split, SplitKind, Submission
from server.object_store import S3Store
from server.runs import ChunkInputs, Rejected, ScoringJob, score_chunk
from server.runs._score import SPLIT_UNREADABLE
from server.services.pictures import picture_scenes
from server.services.splits import register_split, scene_starts, split_tokens, stage_mapping
from server.settings import get_settings
from server.shared_caches import fetch_caches, publish_caches, scene_hashes
from server.split_store import (
    SplitStoreError,
    evict,
    local_scenes,
    mirror_dir,
    split_stages,
)
from server.storage import store_file


def _upload_split(directory: Path) -> S3Store:
    store = fresh_s3_store()
    for path in sorted((directory / "scenes").iterdir()):
        store.put_bytes(f"scenes/{path.name}", path.read_bytes())
    return store


@pytest.fixture
def machine(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A machine of its own: the data directory get_settings() names (where the scene mirror lives)."""
    monkeypatch.setenv("DATA_DIR", str(tmp_path / "machine"))
    get_settings.cache_clear()
    yield tmp_path / "machine"
    get_settings.cache_clear()


def test_a_stored_split_registers_as_its_directory_would(world: World, machine: Path) -> None:
    store = _upload_split(REFERENCE_DIR)
    with transaction(world.factory) as session:
        split = register_split(session, "stored", store.url)
        assert split.directory == store.url
        assert split.content_hash == split_content_hash(REFERENCE_DIR)
        assert split_tokens(split) == tuple(scene_paths(REFERENCE_DIR))
        starts = scene_starts(session, split)
    assert len(starts) == len(scene_paths(REFERENCE_DIR))
    # Another machine: no scene on its disk, the tokens from the manifest alone.
    shutil.rmtree(machine)
    with world.factory() as session:
        assert split_tokens(session.merge(split)) == tuple(scene_paths(REFERENCE_DIR))
    assert not machine.exists()


def test_a_worker_fetches_only_the_scenes_it_needs_each_checked(world: World, machine: Path) -> None:
    store = _upload_split(REFERENCE_DIR)
    with transaction(world.factory) as session:
        content_hash = register_split(session, "stored", store.url).content_hash
    shutil.rmtree(mirror_dir(content_hash))
    tokens = list(scene_paths(REFERENCE_DIR))
    directory = local_scenes(store.url, content_hash, tokens[:3])
    assert list(scene_paths(directory)) == tokens[:3]
    assert all(
        path.read_bytes() == scene_paths(REFERENCE_DIR)[token].read_bytes()
        for token, path in scene_paths(directory).items()
    )
    name = scene_paths(REFERENCE_DIR)[tokens[3]].name
    store.put_bytes(f"scenes/{name}", b"changed after registration")
    with pytest.raises(SplitStoreError, match=f"{name} is damaged or changed"):
        local_scenes(store.url, content_hash, tokens[3:4])
    store.put_bytes(f"scenes/{name}", b"")  # the object is there, but empty: still refused
    with pytest.raises(SplitStoreError, match="damaged"):
        local_scenes(store.url, content_hash, tokens[3:4])
    with pytest.raises(SplitStoreError, match="manifest .* is missing"):
        local_scenes(store.url, "0" * 64, tokens[:1])


def test_the_mirror_checks_its_bound_when_it_grows_only(
    world: World, machine: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = _upload_split(REFERENCE_DIR)
    with transaction(world.factory) as session:
        content_hash = register_split(session, "stored", store.url).content_hash
    shutil.rmtree(mirror_dir(content_hash))
    checks: list[Path] = []
    monkeypatch.setattr(split_store, "evict", lambda root, *_: checks.append(root))
    tokens = list(scene_paths(REFERENCE_DIR))
    local_scenes(store.url, content_hash, tokens[:2])
    assert checks == [mirror_dir(content_hash).parent]
    local_scenes(store.url, content_hash, tokens[:2])  # nothing fetched: the bound was checked at the growth
    assert len(checks) == 1
    local_scenes(store.url, content_hash, tokens[1:3])
    assert len(checks) == 2


def test_the_mirror_keeps_to_its_bound_least_recently_used_first(tmp_path: Path) -> None:
    scenes = tmp_path / "hash" / "scenes"
    scenes.mkdir(parents=True)
    for age, name in enumerate(["new", "middle", "old"]):
        (scenes / name).write_bytes(b"x" * 100)
        os.utime(scenes / name, (time.time() - 1000 * age, time.time() - 1000 * age))
    evict(tmp_path, 250, used_before=time.time() - 1500)
    assert sorted(path.name for path in scenes.iterdir()) == ["middle", "new"]
    evict(tmp_path, 0, used_before=time.time() - 1500)  # used within the time limit: kept
    assert sorted(path.name for path in scenes.iterdir()) == ["middle", "new"]


def test_a_metric_cache_built_once_is_read_by_the_other_workers(
    synthetic_split: SplitFixture, tmp_path: Path
) -> None:
    caches = fresh_s3_store()
    scenes = dict(list(scene_hashes(synthetic_split.directory).items())[:2])
    builder, readers = tmp_path / "builder", [tmp_path / f"reader{n}" for n in range(2)]
    builder.mkdir()
    assert fetch_caches(caches, builder, scenes).unbuilt == list(scenes)  # the store has none yet
    for token in scenes:  # as the engine builds them
        shutil.copy(cache_path(synthetic_split.cache_dir, token), cache_path(builder, token))
    # Two workers that built the same entries publish at once: each entry is stored once.
    with ThreadPoolExecutor(2) as pool:
        published = list(pool.map(lambda _: publish_caches(caches, builder, scenes), range(2)))
    assert sum(published) == len(scenes)
    for reader in readers:
        reader.mkdir()
        fetched = fetch_caches(caches, reader, scenes)
        assert fetched.unbuilt == []
        for token in scenes:
            assert fetched.caches[token] == cache_path(builder, token).read_bytes()
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    key = next(iter(caches.keys("")))
    caches.put_bytes(key, b"not a cache file")
    assert len(fetch_caches(caches, damaged, scenes).unbuilt) == 1  # rebuilt, not read


def test_a_changed_scene_or_a_lost_file_fails_the_run_naming_the_object(world: World, machine: Path) -> None:
    store = _upload_split(REFERENCE_DIR)
    with transaction(world.factory) as session:
        content_hash = register_split(session, "stored", store.url).content_hash
    shutil.rmtree(mirror_dir(content_hash))
    uploads = fresh_s3_store()
    data = (REFERENCE_DIR / "submissions" / "human.json").read_bytes()
    sha256 = hashlib.sha256(data).hexdigest()
    tokens = tuple(scene_paths(REFERENCE_DIR))
    job = ScoringJob(
        1,
        1,
        "human.json",
        store_file(uploads, sha256, io.BytesIO(data)),
        sha256,
        "stored",
        store.url,
        content_hash,
        SplitKind.log_replay,
        1,
        ("v1.1",),
    )
    chunk = ChunkInputs(1, job, tokens[:2], (), isolated=False)
    store.put_bytes(f"scenes/{scene_paths(REFERENCE_DIR)[tokens[1]].name}", b"changed")
    with pytest.raises(Rejected) as rejected:
        score_chunk(chunk, uploads, machine / "cache")
    assert rejected.value.message == SPLIT_UNREADABLE and "s3://" not in rejected.value.message  # the team's
    assert f"{store.url}/scenes/{tokens[1]}" in str(rejected.value.detail)  # the organisers'
    unregistered = dataclasses.replace(job, run=3, split_hash="0" * 64)  # no manifest under this hash
    with pytest.raises(Rejected) as rejected:
        score_chunk(dataclasses.replace(chunk, job=unregistered), uploads, machine / "cache")
    assert rejected.value.message == SPLIT_UNREADABLE and "manifest" in str(rejected.value.detail)
    uploads.put_bytes(job.stored_name, b"")  # the upload's bytes lost in the store
    with pytest.raises(Rejected) as rejected:
        score_chunk(
            dataclasses.replace(chunk, job=dataclasses.replace(job, run=2)), uploads, machine / "cache"
        )
    assert "damaged" in rejected.value.message and uploads.url in str(rejected.value.detail)


def test_a_token_whose_cache_is_in_the_store_is_scored_without_its_scene(
    world: World, machine: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A worker with an empty disk reads the published caches of a chunk's tokens and fetches no scene of
    theirs; the scene of a token whose cache the store lacks is fetched, its cache built and published. The
    rows equal those of the same chunk on the split's directory, bit for bit."""
    store = _upload_split(REFERENCE_DIR)
    with transaction(world.factory) as session:
        content_hash = register_split(session, "stored", store.url).content_hash
    uploads, caches = fresh_s3_store(), fresh_s3_store()
    data = (REFERENCE_DIR / "submissions" / "human.json").read_bytes()
    sha256 = hashlib.sha256(data).hexdigest()
    stored_name = store_file(uploads, sha256, io.BytesIO(data))
    kind, versions = SplitKind.log_replay, ("v1.1",)
    job = ScoringJob(1, 1, "human.json", stored_name, sha256, "s", store.url, content_hash, kind, 1, versions)
    tokens = tuple(scene_paths(REFERENCE_DIR))[:3]
    hashes = {token: scene_hashes(REFERENCE_DIR)[token] for token in tokens}
    on_directory = dataclasses.replace(job, split_source=str(REFERENCE_DIR))
    local = score_chunk(ChunkInputs(1, on_directory, tokens, (), False), uploads, tmp_path / "built")
    publish_caches(caches, tmp_path / "built", {token: hashes[token] for token in tokens[:2]})
    _another_machine(monkeypatch, tmp_path / "worker")
    chunk = score_chunk(ChunkInputs(1, job, tokens, (), False), uploads, tmp_path / "worker-cache", caches)
    assert chunk.rows == local.rows and all(row.valid for row in chunk.rows["v1.1"])
    for token in tokens:  # two caches fetched (the engine read them from memory), the third built
        cached = cache_path(tmp_path / "worker-cache", token).read_bytes()
        assert cached == cache_path(tmp_path / "built", token).read_bytes()
    fetched = {path.name for path in (mirror_dir(content_hash) / "scenes").iterdir()}
    assert fetched == {scene_paths(REFERENCE_DIR)[tokens[2]].name}
    (tmp_path / "reader").mkdir()
    assert fetch_caches(caches, tmp_path / "reader", hashes).unbuilt == []  # the cache built was published


def _stored_two_stage_split() -> S3Store:
    store = _upload_split(EXCERPT)
    store.put_bytes(MAPPING_FILE, (EXCERPT / MAPPING_FILE).read_bytes())
    return store


def _another_machine(monkeypatch: pytest.MonkeyPatch, directory: Path) -> Path:
    """Become another machine: another data directory (its own scene mirror), nothing this process kept."""
    monkeypatch.setenv("DATA_DIR", str(directory))
    get_settings.cache_clear()
    return directory


def test_a_stored_two_stage_split_registers_with_its_stage_mapping(
    world: World, machine: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The manifest carries the stage mapping's sha256, so the split's hash is its directory's; another machine
    reads the mapping from the store (checked), the tokens from the manifest, and no scene."""
    store = _stored_two_stage_split()
    with transaction(world.factory) as session:
        split = register_split(session, "stored-two-stage", store.url)
        assert (split.kind, split.directory) == (SplitKind.two_stage, store.url)
        assert split.content_hash == split_content_hash(EXCERPT)
        content_hash = split.content_hash
    other = _another_machine(monkeypatch, machine.parent / "other")
    with world.factory() as session:
        split = session.merge(split)
        assert stage_mapping(split) == EXCERPT_STAGES
        assert split_tokens(split) == EXCERPT_STAGES.stage_one_tokens + EXCERPT_STAGES.stage_two_tokens
    assert [path.relative_to(other) for path in other.rglob("*") if path.is_file()] == [
        mirror_dir(content_hash).relative_to(other) / MAPPING_FILE
    ]
    _another_machine(monkeypatch, machine.parent / "third")
    store.put_bytes(MAPPING_FILE, b'{"changed": true}')
    with pytest.raises(SplitStoreError, match=f"{MAPPING_FILE} is damaged or changed"):
        split_stages(store.url, content_hash)
    boto3.client("s3").delete_object(Bucket=store.bucket, Key=f"{store.prefix}/{MAPPING_FILE}")
    with pytest.raises(SplitStoreError, match=f"{MAPPING_FILE} is missing"):
        split_stages(store.url, content_hash)


def test_a_worker_scores_a_stored_two_stage_group_from_its_scenes_alone(
    world: World, machine: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A worker with an empty disk scores a chunk of one group (its synthetic scenes included) and fetches
    those scenes only; its rows equal those of the same chunk on the split's directory, bit for bit."""
    store = _stored_two_stage_split()
    with transaction(world.factory) as session:
        content_hash = register_split(session, "stored-two-stage", store.url).content_hash
    _another_machine(monkeypatch, tmp_path / "worker")
    uploads = fresh_s3_store()
    data = dump_two_stage_submission_json(family_submission("swerve_left_fast"))
    sha256 = hashlib.sha256(data).hexdigest()
    stored = store_file(uploads, sha256, io.BytesIO(data))
    [group, *_] = EXCERPT_STAGES.groups or ()
    kind, versions = SplitKind.two_stage, ("v2.2-two-stage",)
    job = ScoringJob(1, 1, "two.json", stored, sha256, "s", store.url, content_hash, kind, 1, versions)
    rows = {}
    for source, cache in ((store.url, tmp_path / "cache"), (str(EXCERPT), tmp_path / "local-cache")):
        chunk_job = dataclasses.replace(job, split_source=source)
        chunk = score_chunk(ChunkInputs(1, chunk_job, group.tokens, (), isolated=False), uploads, cache)
        rows[source] = chunk.rows["v2.2-two-stage"]
    fetched = {path.name for path in (mirror_dir(content_hash) / "scenes").iterdir()}
    assert fetched == {scene_paths(EXCERPT)[token].name for token in group.tokens}
    assert len(fetched) < len(scene_paths(EXCERPT))
    assert any(len(token) == 17 for token in group.tokens)  # synthetic scenes among them
    assert len(rows[store.url]) == len(group.tokens) and rows[store.url] == rows[str(EXCERPT)]
    # A machine that finds the stage mapping changed fails the run, naming the object for the organisers.
    _another_machine(monkeypatch, tmp_path / "third")
    store.put_bytes(MAPPING_FILE, b"{}")
    with pytest.raises(Rejected) as rejected:
        score_chunk(
            ChunkInputs(1, dataclasses.replace(job, run=2), group.tokens, (), False), uploads, tmp_path
        )
    assert rejected.value.message == SPLIT_UNREADABLE
    assert f"{store.url}/{MAPPING_FILE} is damaged or changed" in str(rejected.value.detail)


def test_the_command_line_registers_a_stored_two_stage_split_with_its_baselines(machine: Path) -> None:
    """`navsim-lb admin register-split NAME s3://...` of a two-stage split: a two-stage split, its two
    baselines queued in the two-stage form."""
    store = _stored_two_stage_split()
    app = typer.Typer()
    register(app)
    runner = CliRunner()
    for command in (["db", "upgrade"], ["admin", "register-split", "navhard", store.url]):
        result = runner.invoke(app, command)
        assert result.exit_code == 0, result.output
    assert "baselines queued as submissions" in " ".join(result.output.split())
    engine = make_engine(get_settings().database_url)
    with make_session_factory(engine)() as session:
        split = session.scalars(select(Split).where(Split.name == "navhard")).one()
        assert (split.kind, split.directory, split.token_count) == (SplitKind.two_stage, store.url, 36)
        baselines = session.scalars(select(Submission).where(Submission.split_id == split.id)).all()
        assert len(baselines) == 2 and all(b.is_baseline and b.token_count == 36 for b in baselines)
    engine.dispose()


def test_a_picture_of_a_stored_two_stage_token_reads_its_scene_and_its_synthetic_starts_only(
    world: World, machine: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The drill-down of a stage-one token draws its synthetic starts with their weights: on a machine with
    none of the split's scenes, the token's and its starts' scenes are fetched, and the starts and weights
    equal those of the split's directory."""
    store = _stored_two_stage_split()
    with transaction(world.factory) as session:
        split = register_split(session, "stored-two-stage", store.url)
    _another_machine(monkeypatch, tmp_path / "api")
    [group, *_] = EXCERPT_STAGES.groups or ()
    poses = family_poses("human")[group.original]
    with world.factory() as session:
        directory = picture_scenes(session.merge(split), group.original)
    assert set(scene_paths(directory)) == {group.original, *group.now_tokens}
    version = "v2.2-two-stage"
    stored, local = (
        explain_split_token(where, tmp_path / "cache", group.original, poses, version).synthetic_starts
        for where in (directory, EXCERPT)
    )
    assert stored is not None and local is not None and stored.tokens == local.tokens == group.now_tokens
    assert np.array_equal(stored.start_poses, local.start_poses)
    assert np.array_equal(stored.weights.weight, local.weights.weight)
