"""Metric caches shared between workers through the object store: built once, read by every other machine.

A cache file (scorer.cache) is valid for one scene file and one engine (its OpenBLAS kernels included), so
in the store it is named by exactly that: `<engine key>/<scene sha256>.nlc`, the engine key a hash of
`engine_provenance()`. Before a chunk is scored, each of its scenes whose local cache is missing or stale is
fetched from the store when there (its key checked: a damaged or foreign object is ignored and rebuilt) and
handed to the engine in memory; the ones the store lacks are built by the engine as before, then published
with a conditional write, so of two workers building the same entry at once one stores it and the other's
identical build is dropped. Publishing is best effort: a cache that could not be published is only built
again elsewhere.

One object per token costs a GET per token, and a GET's cost is CPU (the client's under the interpreter's
lock, the store's), about as much as scoring the token. So the caches of a block of tokens are also published
as one pack, `<engine key>/packs/<sha256 of the members' scene hashes>.nlp`: the blocks are the split's tokens
in the order chunks are planned, cut every PACK_TOKENS (server.runs._plan, which plans chunks of whole
blocks), so the packs one run publishes are those every later run fetches. A chunk reads a block's pack when it
holds every member and lacks the caches of at least half of them; each member is checked as a single cache is
(a damaged pack, or member, falls back to the single objects). The worker that ends a chunk holding every
member of a block whose pack the store lacked publishes it, with the same conditional write.

A machine keeps what it fetched, for its later chunks and runs: a whole pack as one file under its store key
in the cache directory (read again and checked as the store's), a single object as the engine's own cache
file. Writing a pack's 64 members as files cost a chunk about as long as its GETs on a loaded host, and
written on a thread beside the engine they waited for the interpreter's lock.
"""

from __future__ import annotations

import hashlib
import json
import logging
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from scorer.blas import engine_provenance
from scorer.cache import cache_file_key, cache_path
from scorer.files import write_atomically
from server.object_store import ObjectStore, StoreUnavailable, get_many

log = logging.getLogger(__name__)

_PACK_MAGIC = b"NLPACK1\n"
_PACK_HEADER = struct.Struct("<I")  # the length of the JSON list of (scene hash, size) that follows


def engine_key() -> str:
    """Return the short name of the engine that computes what is cached (its version and OpenBLAS kernels)."""
    return hashlib.sha256(engine_provenance().encode()).hexdigest()[:16]


def _key(scene_hash: str) -> str:
    return f"{engine_key()}/{scene_hash}.nlc"


def _pack_key(block: Mapping[str, str]) -> str:
    members = hashlib.sha256("\n".join(block.values()).encode()).hexdigest()
    return f"{engine_key()}/packs/{members}.nlp"


def _pack(caches: Sequence[tuple[str, bytes]]) -> bytes:
    """Return the pack of the caches (scene hash, cache file bytes), in block order."""
    header = json.dumps([[scene_hash, len(data)] for scene_hash, data in caches]).encode()
    return b"".join([_PACK_MAGIC, _PACK_HEADER.pack(len(header)), header, *(data for _, data in caches)])


def _members(pack: bytes) -> dict[str, bytes]:
    """Return scene hash -> cache file bytes of a pack; empty when the pack is not whole (each member is still
    to be checked: `_holds`)."""
    start = len(_PACK_MAGIC) + _PACK_HEADER.size
    try:
        if not pack.startswith(_PACK_MAGIC):
            return {}
        (length,) = _PACK_HEADER.unpack_from(pack, len(_PACK_MAGIC))
        members, offset = {}, start + length
        for scene_hash, size in json.loads(pack[start : start + length]):
            members[str(scene_hash)] = pack[offset : offset + int(size)]
            offset += int(size)
    except (ValueError, TypeError, struct.error):
        return {}
    return members if offset == len(pack) else {}


def _holds(data: bytes, scene_hash: str) -> bool:
    key = cache_file_key(data)
    return key is not None and (key.scene_hash, key.engine_version) == (scene_hash, engine_provenance())


def _local(cache_dir: Path, token: str) -> bytes:
    return _read(cache_path(cache_dir, token))


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError:
        return b""


def scene_hashes(split_dir: Path) -> dict[str, str]:
    """Return token -> the sha256 of its scene file, for every scene of a split directory (what its metric
    caches are named by in the store)."""
    from scorer.scene import scene_file_hash, scene_paths

    return {token: scene_file_hash(path) for token, path in scene_paths(split_dir).items()}


@dataclass(frozen=True)
class FetchedCaches:
    """A chunk's caches read from the store or this machine's copies of its packs, token -> cache file bytes
    (each checked: the engine reads them from memory), and what is left to do: the tokens whose cache the
    engine builds (`publish_caches`), and the blocks whose pack the store lacked (`publish_packs`, once the
    chunk is scored)."""

    caches: dict[str, bytes]
    unbuilt: list[str]
    unpacked: list[tuple[str, ...]]


def fetch_caches(
    store: ObjectStore, cache_dir: Path, hashes: Mapping[str, str], blocks: Sequence[Sequence[str]] = ()
) -> FetchedCaches:
    """Read the caches of the scenes (token -> the scene file's sha256) that lack a valid one in `cache_dir`:
    a block's from its pack when the chunk holds every member (`blocks`, each a block of `hashes`' tokens)
    and lacks at least half of them (this machine's copy of the pack, else the store's, then kept as one file
    in `cache_dir`), the others one object each from the store (each kept in `cache_dir` as the engine's
    own would be)."""
    wanted = {
        token: scene_hash
        for token, scene_hash in hashes.items()
        if not _holds(_local(cache_dir, token), scene_hash)
    }
    held = [
        {token: hashes[token] for token in block}
        for block in blocks
        if hashes.keys() >= {*block} and 2 * sum(token in wanted for token in block) >= len(block)
    ]
    packed = {_pack_key(block): block for block in held}
    members = {key: _checked_members(_read(cache_dir / key), block) for key, block in packed.items()}
    uncopied = [key for key, block in packed.items() if len(members[key]) < len(block)]
    caches, unpacked = {}, []
    for key, pack in get_many(store, uncopied).items():
        members[key] = _checked_members(pack or b"", packed[key])
        if pack is None:  # a damaged pack stays (the write is conditional): its blocks are read singly
            unpacked.append(tuple(packed[key]))
        elif len(members[key]) == len(packed[key]):  # one file where 64 would cost a chunk its GETs' time
            write_atomically(cache_dir / key, pack, durable=False)
        elif not members[key]:
            log.warning("metric cache pack %s/%s is damaged: read one by one", store.url, key)
    for key, block in packed.items():
        for token in block:
            if token in wanted and token in members[key]:
                caches[token] = members[key][token]
                del wanted[token]
    unbuilt = _fetch_singly(store, cache_dir, wanted, caches)
    return FetchedCaches(caches, unbuilt, unpacked)


def _checked_members(pack: bytes, block: Mapping[str, str]) -> dict[str, bytes]:
    """Return token -> cache file bytes of the block's (token -> scene hash) members a pack holds whole."""
    members = _members(pack)
    found = {token: members.get(scene_hash, b"") for token, scene_hash in block.items()}
    return {token: data for token, data in found.items() if _holds(data, block[token])}


def _fetch_singly(
    store: ObjectStore, cache_dir: Path, wanted: Mapping[str, str], caches: dict[str, bytes]
) -> list[str]:
    """Read the store's cache of each scene into `caches` and `cache_dir`, one object each; return the
    tokens it had none (or a damaged one) for."""
    fetched = get_many(store, (_key(scene_hash) for scene_hash in wanted.values()))
    unbuilt = []
    for token, scene_hash in wanted.items():
        data = fetched[_key(scene_hash)]
        if data is None:
            unbuilt.append(token)
            continue
        if not _holds(data, scene_hash):
            log.warning("metric cache %s/%s is damaged or foreign: rebuilt", store.url, _key(scene_hash))
            unbuilt.append(token)
            continue
        caches[token] = data
    keep_caches(cache_dir, {token: caches[token] for token in wanted if token in caches})
    return unbuilt


def keep_caches(cache_dir: Path, caches: Mapping[str, bytes]) -> None:
    """Write caches (token -> cache file bytes) into `cache_dir`, one file each, as the engine reads them."""
    for token, data in caches.items():
        write_atomically(cache_path(cache_dir, token), data, durable=False)


def publish_caches(store: ObjectStore, cache_dir: Path, hashes: Mapping[str, str]) -> int:
    """Publish the local caches of the scenes (token -> the scene file's sha256) the store lacked; return how
    many this call stored (another worker may have stored the same entry first)."""
    published = 0
    for token, scene_hash in hashes.items():
        data = _local(cache_dir, token)
        if not _holds(data, scene_hash):
            continue  # the engine could not build it (the token's row says why)
        try:
            published += store.put_if_absent(_key(scene_hash), data)
        except StoreUnavailable as error:
            log.warning("metric caches not published (built again elsewhere): %s", error)
            break
    return published


def publish_packs(
    store: ObjectStore, cache_dir: Path, hashes: Mapping[str, str], blocks: Iterable[Sequence[str]]
) -> int:
    """Publish the pack of each block (its tokens, of `hashes`: token -> the scene file's sha256) whose every
    member has a valid local cache; return how many this call stored."""
    published = 0
    for tokens in blocks:
        block = {token: hashes[token] for token in tokens}
        caches = [(scene_hash, _local(cache_dir, token)) for token, scene_hash in block.items()]
        if not all(_holds(data, scene_hash) for scene_hash, data in caches):
            continue  # a member the engine could not build: its chunks read the others one by one
        try:
            published += store.put_if_absent(_pack_key(block), _pack(caches))
        except StoreUnavailable as error:
            log.warning("metric cache packs not published (published by a later chunk): %s", error)
            break
    return published
