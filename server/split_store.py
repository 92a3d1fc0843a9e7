"""Splits whose scenes live in an object store (`s3://bucket/prefix`, holding `scenes/<token>.json[.gz]`), and
each machine's read-through copy of the scenes it scores.

Registering such a split reads every scene once (the split's content hash covers each scene file's sha256) and
publishes its manifest, token -> (file name, sha256), beside its scenes under that content hash. Every other
machine reads the manifest instead of the scenes: the API its tokens, a worker the scenes whose metric caches
it builds (a cache is named by its scene's sha256, the manifest's), each fetched into a local mirror and
checked against its sha256 (the manifest is checked against the split's hash in the database, so neither can
be swapped). The mirror is bounded: whenever it grows, past `split_cache_bytes` the scenes used least
recently are removed, never one used within the task time limit (a chunk of another process may be about to
read it).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from types import MappingProxyType

from scorer.files import write_atomically
from scorer.two_stage.split import MAPPING_FILE, TwoStageSplit, load_two_stage_split
from server.object_store import MissingObject, child, get_many, is_store_url, open_store
from server.settings import get_settings

SCENES = "scenes"
MANIFESTS = ".navsim-lb"  # beside scenes/: the manifests of the splits registered from this prefix
SCENE_SUFFIXES = (".json", ".json.gz")


class SplitStoreError(Exception):
    """A split's scenes or manifest are missing from the store or do not match the registered split: what an
    organiser must restore (`message` names the object)."""


@dataclass(frozen=True)
class Manifest:
    """The scene files of a split in the store: token -> (file name under scenes/, sha256), in token order, and
    a two-stage split's stage mapping (`two_stage.json` beside scenes/): its sha256, None for a one-stage split."""

    source: str
    scenes: Mapping[str, tuple[str, str]]
    mapping: str | None = None

    def content_hash(self) -> str:
        """The split's content hash (scorer.evaluate.split_content_hash), from the sha256s alone."""
        digest = hashlib.sha256()
        for token, (_, sha256) in self.scenes.items():
            digest.update(f"{token}:{sha256}\n".encode())
        if self.mapping is not None:
            digest.update(f"{MAPPING_FILE}:{self.mapping}\n".encode())
        return digest.hexdigest()

    def to_json(self) -> bytes:
        document = {"source": self.source, "scenes": self.scenes, "mapping": self.mapping}
        return json.dumps(document, sort_keys=True).encode()


def is_stored_split(location: str) -> bool:
    """Return whether a registered split's location is an object store rather than a local directory."""
    return is_store_url(location)


def mirror_dir(content_hash: str) -> Path:
    """Return this machine's copy of a stored split (holding scenes/): what the engine reads."""
    return get_settings().data_dir / "split-cache" / content_hash


def _manifest_key(content_hash: str) -> str:
    return f"{MANIFESTS}/{content_hash}.json"


def _token_of(name: str) -> str | None:
    return next((name.removesuffix(suffix) for suffix in SCENE_SUFFIXES if name.endswith(suffix)), None)


def fetch_whole_split(source: str) -> Path:
    """Copy every scene of the split at `source` into this machine's mirror, publish the split's manifest
    beside its scenes, and return the mirror (to register the split from, and to score its baselines)."""
    from scorer.scene import scene_file_hash

    store = open_store(source)
    scenes_store = child(store, SCENES)
    names = {token: name for name in scenes_store.keys("") if (token := _token_of(name)) and "/" not in name}
    staging = mirror_dir(f"registering-{hashlib.sha256(source.encode()).hexdigest()}")
    shutil.rmtree(staging, ignore_errors=True)
    (staging / SCENES).mkdir(parents=True)
    scenes = {}
    for token in sorted(names):
        path = staging / SCENES / names[token]
        scenes_store.download(names[token], path)
        scenes[token] = (names[token], scene_file_hash(path))
    try:  # a two-stage split's stage mapping
        document = store.get(MAPPING_FILE)
    except MissingObject:
        mapping = None
    else:
        write_atomically(staging / MAPPING_FILE, document, durable=False)
        mapping = hashlib.sha256(document).hexdigest()
    manifest = Manifest(source, scenes, mapping)
    store.put_if_absent(_manifest_key(manifest.content_hash()), manifest.to_json())
    directory = mirror_dir(manifest.content_hash())
    shutil.rmtree(directory, ignore_errors=True)  # a part left by an interrupted fetch
    staging.rename(directory)
    return directory


@lru_cache(maxsize=8)
def split_manifest(source: str, content_hash: str) -> Manifest:
    """Return the manifest of the stored split at `source` with this content hash, checked against it."""
    store = open_store(source)
    where = f"{store.url}/{_manifest_key(content_hash)}"
    try:
        data = json.loads(store.get(_manifest_key(content_hash)))
        scenes = {token: tuple(entry) for token, entry in data["scenes"].items()}
        manifest = Manifest(data["source"], scenes, data.get("mapping"))
    except MissingObject:
        raise SplitStoreError(f"the split's manifest {where} is missing: register the split again") from None
    except (ValueError, KeyError, TypeError, AttributeError):
        manifest = Manifest("", {})
    if manifest.content_hash() != content_hash:
        raise SplitStoreError(f"the split's manifest {where} is damaged: register the split again")
    return manifest


def split_tokens(location: str, content_hash: str) -> tuple[str, ...]:
    """Return the tokens of a registered split in token order, from its manifest when it is stored."""
    from scorer.scene import scene_paths

    if is_stored_split(location):
        return tuple(split_manifest(location, content_hash).scenes)
    return tuple(scene_paths(location))


def split_stages(location: str, content_hash: str) -> TwoStageSplit:
    """Return the stage mapping of a registered two-stage split: a local split's `two_stage.json`; a stored
    split's, kept in this machine's mirror (fetched once, checked against the manifest's sha256), its tokens
    those of the manifest (the mirror holds only the scenes used here)."""
    if not is_stored_split(location):
        return load_two_stage_split(Path(location))
    return _stored_stages(location, content_hash, mirror_dir(content_hash))


@lru_cache(maxsize=8)
def _stored_stages(location: str, content_hash: str, mirror: Path) -> TwoStageSplit:
    """Return the stage mapping of a stored split, kept in `mirror` (the data directory's, a key of the cache)."""
    manifest = split_manifest(location, content_hash)
    store = open_store(location)
    where = f"{store.url}/{MAPPING_FILE}"
    if manifest.mapping is None:
        raise SplitStoreError(f"the split at {store.url} was registered without a stage mapping")
    path = mirror / MAPPING_FILE
    if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != manifest.mapping:
        try:
            data = store.get(MAPPING_FILE)
        except MissingObject:
            raise SplitStoreError(f"the split's stage mapping {where} is missing; restore it") from None
        if hashlib.sha256(data).hexdigest() != manifest.mapping:
            raise SplitStoreError(
                f"the split's stage mapping {where} is damaged or changed: its sha256 "
                "differs from the registered split's; restore it"
            )
        write_atomically(path, data, durable=False)
    return load_two_stage_split(mirror, manifest.scenes)


def stored_scene_files(location: str, content_hash: str) -> tuple[Mapping[str, Path], Mapping[str, str]]:
    """Return, for each token of a stored split, its scene file in this machine's mirror (there or not:
    `local_scenes` fetches it) and its registered sha256, from the manifest: what a worker scores a chunk
    with, without listing the mirror or fetching the scene of a token whose metric cache it has."""
    return _stored_scene_files(location, content_hash, mirror_dir(content_hash))


@lru_cache(maxsize=8)
def _stored_scene_files(
    location: str, content_hash: str, mirror: Path
) -> tuple[Mapping[str, Path], Mapping[str, str]]:
    """`stored_scene_files` in `mirror` (the data directory's, a key of the cache)."""
    scenes = split_manifest(location, content_hash).scenes
    paths = {token: mirror / SCENES / name for token, (name, _) in scenes.items()}
    return MappingProxyType(paths), MappingProxyType({token: sha256 for token, (_, sha256) in scenes.items()})


def local_scenes(location: str, content_hash: str, tokens: Iterable[str]) -> Path:
    """Return a local directory holding at least the scenes of `tokens` (those of the split): a local split's
    own; for a stored split, this machine's mirror, with the missing scenes fetched, each checked against the
    manifest's sha256 (SplitStoreError), then kept within its bound."""
    if not is_stored_split(location):
        return Path(location)
    manifest = split_manifest(location, content_hash)
    directory = mirror_dir(content_hash)
    scenes_store = child(open_store(location), SCENES)
    now = time.time()
    missing = []
    for token in tokens:
        if token not in manifest.scenes:
            continue  # the engine reports it as not part of the split
        path = directory / SCENES / manifest.scenes[token][0]
        if path.exists():
            os.utime(path, (now, now))  # used: the last to be evicted
        else:
            missing.append(token)
    fetched = get_many(scenes_store, (manifest.scenes[token][0] for token in missing))
    for token in missing:
        name, sha256 = manifest.scenes[token]
        path, data = directory / SCENES / name, fetched[name]
        if data is None:
            raise SplitStoreError(f"scene {scenes_store.url}/{name} of the split is missing")
        if hashlib.sha256(data).hexdigest() != sha256:
            raise SplitStoreError(
                f"scene {scenes_store.url}/{name} is damaged or changed: its sha256 differs from the "
                "registered split's; restore it"
            )
        write_atomically(path, data, durable=False)
    if missing:  # each growth is followed by a check of the bound, by the process that grew the mirror
        settings = get_settings()
        evict(directory.parent, settings.split_cache_bytes, now - settings.task_time_limit)
    return directory


def evict(root: Path, bound_bytes: int, used_before: float) -> None:
    """Remove the scenes under `root` used least recently (their modification time) until the rest fit in
    `bound_bytes`; a scene used after `used_before` stays, whatever the bound."""
    files = _mirrored_scenes(root)
    total = sum(status.st_size for status, _ in files)
    for status, path in sorted(files, key=lambda item: item[0].st_mtime):
        if total <= bound_bytes or status.st_mtime > used_before:
            return
        Path(path).unlink(missing_ok=True)
        total -= status.st_size


def _mirrored_scenes(root: Path) -> list[tuple[os.stat_result, str]]:
    """Return the status and path of each scene file under `root`/*/scenes/. A cold worker checks the bound
    after every chunk, over every scene mirrored so far (12,000 on navtest): os.scandir reads each file's
    status once, where Path.glob with is_file and stat read it twice and build a Path each (~3x the CPU)."""
    found = []
    with os.scandir(root) as splits:
        for split in splits:
            try:
                with os.scandir(os.path.join(split.path, SCENES)) as scenes:
                    found += [
                        (entry.stat(follow_symlinks=False), entry.path)
                        for entry in scenes
                        if entry.is_file(follow_symlinks=False)
                    ]
            except (FileNotFoundError, NotADirectoryError):
                continue  # a file beside the mirrors, or a mirror being renamed into place
    return found
