"""The logged human's future positions of a split's original scenes, which the integrity checks compare each
entry with: computed once per split and engine, then read by every worker, as the metric caches are.

Computing them loads every scene (6-35 ms a scene: 12 s for a 2,000-scene split, over a minute for navtest),
which a check must not pay again in each process or on each machine: it would hold a consumer that chunks wait
for. They are named by what decides them, the split's content hash (its scenes' bytes) and the engine
(`engine_key`: version and OpenBLAS kernels, as for the metric caches): `human-futures/<engine>/<split>.npz`,
kept under the cache directory and, with an object store, published under the same key beside the metric
caches (a conditional write: of two workers computing them at once, one stores them). A worker without a
local copy fetches the store's; a file that holds other tokens or shapes than the split's (damaged, foreign)
is ignored and computed again. Publishing is best effort: futures not published are only computed elsewhere.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np

from scorer.files import write_atomically
from scorer.geometry import FloatArray
from server.object_store import MissingObject, ObjectStore, StoreUnavailable
from server.shared_caches import engine_key

log = logging.getLogger(__name__)
POSES = 8


def _key(content_hash: str) -> str:
    return f"human-futures/{engine_key()}/{content_hash}.npz"


def _original_scenes(split_dir: Path) -> dict[str, Path]:
    """Return token -> scene file of the split's original scenes (synthetic ones have no logged human)."""
    from scorer.human import is_synthetic
    from scorer.scene import scene_paths

    return {token: scene for token, scene in scene_paths(split_dir).items() if not is_synthetic(token)}


def _decoded(data: bytes, tokens: list[str]) -> dict[str, FloatArray] | None:
    """Return the futures a file holds when they are exactly the split's tokens' (8, 2) positions, else None."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as stored:
            stored_tokens, positions = stored["tokens"].tolist(), stored["positions"]
    except (OSError, ValueError, KeyError, EOFError):
        return None
    if stored_tokens != tokens or positions.shape != (len(tokens), POSES, 2):
        return None
    return dict(zip(stored_tokens, positions, strict=True))


def _encoded(futures: dict[str, FloatArray]) -> bytes:
    buffer = io.BytesIO()
    positions = np.array(list(futures.values()), dtype=np.float64).reshape(len(futures), POSES, 2)
    np.savez(buffer, tokens=np.array(list(futures), dtype=str), positions=positions)
    return buffer.getvalue()


def compute_futures(scenes: dict[str, Path]) -> dict[str, FloatArray]:
    """Return each scene's logged human future positions (8, 2), read from its file (the costly part)."""
    from scorer.human import human_future_poses
    from scorer.scene import load_scene

    return {token: human_future_poses(load_scene(scene))[:, :2] for token, scene in scenes.items()}


def _fetched(store: ObjectStore, key: str) -> bytes:
    try:
        return store.get(key)
    except MissingObject:
        return b""
    except StoreUnavailable as error:
        log.warning("human futures %s not fetched (computed here): %s", key, error)
        return b""


def human_futures(
    split_dir: Path, content_hash: str, cache_dir: Path, store: ObjectStore | None
) -> dict[str, FloatArray]:
    """Return token -> the logged human's 8 future positions (8, 2) of each original scene of a split: the
    local copy, else the store's, else computed from the scenes and kept (and published to the store)."""
    scenes = _original_scenes(split_dir)
    tokens = list(scenes)
    key = _key(content_hash)
    local = cache_dir / key
    try:
        futures = _decoded(local.read_bytes(), tokens)
    except OSError:
        futures = None
    if futures is not None:
        return futures
    data = b""
    if store is not None and (data := _fetched(store, key)):
        futures = _decoded(data, tokens)
        if futures is None:
            log.warning("human futures %s/%s are damaged or foreign: computed again", store.url, key)
    if futures is None:
        futures = compute_futures(scenes)
        data = _encoded(futures)
        if store is not None:
            try:
                store.put_if_absent(key, data)
            except StoreUnavailable as error:
                log.warning("human futures %s not published (computed again elsewhere): %s", key, error)
    write_atomically(local, data, durable=False)  # computed or fetched again when lost
    return futures
