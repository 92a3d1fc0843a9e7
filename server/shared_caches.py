"""Metric caches shared between workers through the object store: built once, read by every other machine.

A cache file (scorer.cache) is valid for one scene file and one engine (its OpenBLAS kernels included), so
in the store it is named by exactly that: `<engine key>/<scene sha256>.nlc`, the engine key a hash of
`engine_provenance()`. Before a chunk is scored, each of its scenes whose local cache is missing or stale is
fetched from the store when there (its key checked: a damaged or foreign object is ignored and rebuilt); the
ones the store lacks are built by the engine as before, then published with a conditional write, so of two
workers building the same entry at once one stores it and the other's identical build is dropped. Publishing
is best effort: a cache that could not be published is only built again elsewhere.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Mapping
from pathlib import Path

from scorer.blas import engine_provenance
from scorer.cache import cache_file_key, cache_path
from scorer.files import write_atomically
from server.object_store import ObjectStore, StoreUnavailable, get_many

log = logging.getLogger(__name__)


def engine_key() -> str:
    """Return the short name of the engine that computes what is cached (its version and OpenBLAS kernels)."""
    return hashlib.sha256(engine_provenance().encode()).hexdigest()[:16]


def _key(scene_hash: str) -> str:
    return f"{engine_key()}/{scene_hash}.nlc"


def _holds(data: bytes, scene_hash: str) -> bool:
    key = cache_file_key(data)
    return key is not None and (key.scene_hash, key.engine_version) == (scene_hash, engine_provenance())


def _local(cache_dir: Path, token: str) -> bytes:
    try:
        return cache_path(cache_dir, token).read_bytes()
    except OSError:
        return b""


def scene_hashes(split_dir: Path) -> dict[str, str]:
    """Return token -> the sha256 of its scene file, for every scene of a split directory (what its metric
    caches are named by in the store)."""
    from scorer.scene import scene_file_hash, scene_paths

    return {token: scene_file_hash(path) for token, path in scene_paths(split_dir).items()}


def fetch_caches(store: ObjectStore, cache_dir: Path, hashes: Mapping[str, str]) -> list[str]:
    """Bring the store's caches of the scenes (token -> the scene file's sha256) that lack a valid local one
    into `cache_dir`; return the tokens the store had none for (the engine builds them: `publish_caches`)."""
    wanted = {
        token: scene_hash
        for token, scene_hash in hashes.items()
        if not _holds(_local(cache_dir, token), scene_hash)
    }
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
        write_atomically(cache_path(cache_dir, token), data, durable=False)
    return unbuilt


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
