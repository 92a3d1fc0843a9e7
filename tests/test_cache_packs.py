"""Metric caches in packs: a block's caches published as one object and read with one GET by a chunk that
holds the whole block; a damaged pack, a partial chunk or a block mostly cached already read the caches one
by one; two publishers of the same pack store it once. Chunks are planned of whole blocks, which depend on the
split alone."""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from object_stores import fresh_s3_store
from server_testing import World, claimed_submission
from worker_testing import SplitFixture

from scorer.cache import cache_path
from scorer.scene import scene_paths, scene_start
from server.db import transaction
from server.models import ScoringChunk, Submission
from server.object_store import LocalStore, ObjectStore
from server.runs import _plan, chunk_inputs, split_blocks, start_chunk
from server.services.splits import scene_starts
from server.shared_caches import (
    _pack,
    _pack_key,
    fetch_caches,
    publish_caches,
    publish_packs,
    scene_hashes,
)


@dataclass(frozen=True)
class CountedStore(LocalStore):
    """A local store that records the keys read."""

    reads: list[str] = field(default_factory=list)

    def get(self, key: str) -> bytes:
        self.reads.append(key)
        return super().get(key)


def _packs(store: LocalStore) -> list[Path]:
    return sorted(store.root.glob("*/packs/*.nlp"))


@dataclass(frozen=True)
class Built:
    """A split's metric caches built in `cache_dir`, its scene hashes and two blocks of 4 tokens."""

    cache_dir: Path
    hashes: dict[str, str]
    blocks: list[tuple[str, ...]]

    def store(self, root: Path, singles: bool, packs: int) -> CountedStore:
        """Return a store holding each token's cache (with `singles`) and the first `packs` blocks' packs."""
        store = CountedStore(root / "store")
        if singles:
            publish_caches(store, self.cache_dir, self.hashes)
        publish_packs(store, self.cache_dir, self.hashes, self.blocks[:packs])
        return store

    def chunk(self, *blocks: Sequence[str]) -> dict[str, str]:
        """Return token -> scene hash of the tokens of `blocks`."""
        return {token: self.hashes[token] for block in blocks for token in block}


@pytest.fixture
def built(synthetic_split: SplitFixture) -> Built:
    starts = {token: scene_start(path) for token, path in scene_paths(synthetic_split.directory).items()}
    ordered = split_blocks(starts)[0]  # the split's 12 tokens are one block of PACK_TOKENS
    hashes = scene_hashes(synthetic_split.directory)
    return Built(synthetic_split.cache_dir, hashes, [ordered[:4], ordered[4:8]])


def _cold(tmp_path: Path, name: str) -> Path:
    directory = tmp_path / name
    directory.mkdir()
    return directory


def _same_caches(caches: Mapping[str, bytes], built: Built, tokens: Iterable[str]) -> bool:
    return caches.keys() == {*tokens} and all(
        data == cache_path(built.cache_dir, token).read_bytes() for token, data in caches.items()
    )


def test_a_whole_block_is_read_with_one_get(built: Built, tmp_path: Path) -> None:
    store = built.store(tmp_path, singles=False, packs=2)
    assert len(_packs(store)) == 2
    chunk = built.chunk(*built.blocks)
    reader = _cold(tmp_path, "reader")
    fetched = fetch_caches(store, reader, chunk, built.blocks)
    assert (fetched.unbuilt, fetched.unpacked) == ([], [])
    assert len(store.reads) == 2  # no single object read (the store holds none)
    assert _same_caches(fetched.caches, built, chunk)
    # Each pack kept whole, as one file: the next chunk or run on this machine reads it instead of the store.
    kept = sorted(path.relative_to(reader) for path in reader.rglob("*") if path.is_file())
    assert kept == sorted(path.relative_to(store.root) for path in _packs(store))
    store.reads.clear()
    again = fetch_caches(store, reader, chunk, built.blocks)
    assert (
        store.reads == [] and again.caches == fetched.caches and (again.unbuilt, again.unpacked) == ([], [])
    )


def test_a_damaged_copy_of_a_pack_is_read_from_the_store_again(built: Built, tmp_path: Path) -> None:
    store, block = built.store(tmp_path, singles=False, packs=1), built.blocks[0]
    reader = _cold(tmp_path, "reader")
    assert fetch_caches(store, reader, built.chunk(block), [block]).unbuilt == []
    (copy,) = reader.rglob("*.nlp")
    copy.write_bytes(copy.read_bytes()[:-10])  # cut short
    store.reads.clear()
    fetched = fetch_caches(store, reader, built.chunk(block), [block])
    assert len(store.reads) == 1 and _same_caches(fetched.caches, built, block)
    assert copy.read_bytes() == _packs(store)[0].read_bytes()  # the copy made whole again


def test_a_partial_chunk_or_a_mostly_cached_block_reads_one_by_one(built: Built, tmp_path: Path) -> None:
    store, block = built.store(tmp_path, singles=True, packs=1), built.blocks[0]
    partial = built.chunk(block[:3])  # the chunk lacks a member: no pack read
    assert fetch_caches(store, _cold(tmp_path, "partial"), partial, [block]).unbuilt == []
    assert len(store.reads) == 3 and not any("/packs/" in key for key in store.reads)
    store.reads.clear()
    mostly = _cold(tmp_path, "mostly")  # three of four members cached here already: the fourth read alone
    for token in block[:3]:
        shutil.copy(cache_path(built.cache_dir, token), cache_path(mostly, token))
    assert fetch_caches(store, mostly, built.chunk(block), [block]).unbuilt == []
    assert len(store.reads) == 1 and "/packs/" not in store.reads[0]


def test_a_damaged_pack_is_ignored_and_a_missing_one_published_after_the_chunk(
    built: Built, tmp_path: Path
) -> None:
    store, (block, other) = built.store(tmp_path, singles=True, packs=1), built.blocks
    (pack,) = _packs(store)
    pack.write_bytes(pack.read_bytes()[:-10])  # cut short
    chunk = built.chunk(block, other)
    reader = _cold(tmp_path, "reader")
    fetched = fetch_caches(store, reader, chunk, [block, other])
    # Both blocks read one by one; only the missing pack is to be published (the damaged one cannot be
    # replaced by a conditional write).
    assert fetched.unbuilt == [] and fetched.unpacked == [other]
    assert len(store.reads) == 2 + len(chunk) and _same_caches(fetched.caches, built, chunk)
    assert not any(reader.rglob("*.nlp"))  # no copy of a damaged pack: each member is kept on its own
    assert publish_packs(store, reader, chunk, fetched.unpacked) == 1
    store.reads.clear()
    assert fetch_caches(store, _cold(tmp_path, "again"), built.chunk(other), [other]).unbuilt == []
    assert len(store.reads) == 1  # the pack published from the reader's caches


def test_a_foreign_member_is_read_alone_and_a_block_with_one_is_not_published(
    built: Built, tmp_path: Path
) -> None:
    store, block = built.store(tmp_path, singles=True, packs=0), built.blocks[0]
    swapped = {token: block[2] if token == block[1] else token for token in block}  # block[1] holds another's
    foreign = _cold(tmp_path, "foreign")  # a worker whose cache of block[1] is another scene's
    for token in block:
        shutil.copy(cache_path(built.cache_dir, swapped[token]), cache_path(foreign, token))
    assert publish_packs(store, foreign, built.hashes, [block]) == 0
    caches = [(built.hashes[token], cache_path(foreign, token).read_bytes()) for token in block]
    store.put_bytes(_pack_key(built.chunk(block)), _pack(caches))  # such a pack published all the same
    fetched = fetch_caches(store, _cold(tmp_path, "reader"), built.chunk(block), [block])
    assert fetched.unbuilt == []
    assert [key.endswith(f"{built.hashes[block[1]]}.nlc") for key in store.reads] == [False, True]
    assert _same_caches(fetched.caches, built, block)


def test_two_publishers_of_a_pack_store_it_once(built: Built, tmp_path: Path) -> None:
    store: ObjectStore = fresh_s3_store()
    with ThreadPoolExecutor(2) as pool:
        published = list(
            pool.map(lambda _: publish_packs(store, built.cache_dir, built.hashes, built.blocks), range(2))
        )
    assert sum(published) == 2
    chunk = built.chunk(*built.blocks)
    assert fetch_caches(store, _cold(tmp_path, "reader"), chunk, built.blocks).unpacked == []


def test_chunks_are_planned_of_whole_blocks_cut_from_the_whole_split(
    world: World, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_plan, "PACK_TOKENS", 4)
    monkeypatch.setattr(_plan, "_blocks_of_split", {})
    submission = claimed_submission(world, b"blocks")
    with transaction(world.factory) as session:
        row = session.get(Submission, submission.id)
        assert row is not None
        assert _plan.token_blocks(session, row.split) == {}  # no index of log frames yet: none is read
        scene_starts(session, row.split)  # planning builds it
        blocks = list(dict.fromkeys(_plan.token_blocks(session, row.split).values()))
        assert all(len(block) == 4 for block in blocks[:-1]) and len(blocks) >= 3
        # Two tokens of the first block already scored (a resumed run): they stay out, the blocks stay.
        todo = [*blocks[0][2:], *blocks[1], *blocks[2]]
        chunk_ids = _plan.plan_chunks(session, row, todo, 8)
        chunks = [session.get(ScoringChunk, chunk_id) for chunk_id in chunk_ids]
        assert [chunk.tokens for chunk in chunks if chunk] == [[*blocks[0][2:], *blocks[1]], list(blocks[2])]
        started = start_chunk(session, chunk_ids[0], 1, "host/1")
        inputs = chunk_inputs(session, submission.id, 1, started, packs=True)
        assert inputs is not None
        assert inputs.packs == (blocks[1],)  # the first block's is not whole in the chunk
        without_store = chunk_inputs(session, submission.id, 1, started)
        assert without_store is not None and without_store.packs == ()  # a local cache reads no pack
