"""Synthetic splits: `<out>/scenes/<token>.json.gz` plus `<out>/split.json`, the same bytes for the same seed.

Scene i of a split is a function of (seed, i) alone, so a larger split with the same seed starts with
the scenes of a smaller one. Tokens are 16 hex digits of sha256(generator version, seed, i): bump
GENERATOR_VERSION whenever the output changes, so that new scenes never share a token (and a cache
entry) with old ones. `split.json` holds `format`, `name`, `seed`, `n`, `generator_version` and, per
scene, the generator's notes (kind, route variant, lanes, ego speed, lead behaviour, ...): a debugging
aid, never an input of the scoring.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from scorer.synth.corridor import corridor_scene
from scorer.synth.draft import Dice, SceneDraft
from scorer.synth.export import encode_scene, scene_document, short_hash
from scorer.synth.intersection import intersection_scene

GENERATOR_VERSION = "navsim-lb-synth/1"
SPLIT_FORMAT = "navsim-lb/synthetic-split"
KINDS = {"straight": 0.22, "curve": 0.2, "intersection": 0.36, "carpark": 0.11, "carpark_start": 0.11}
# Choices stratified over the split (Dice.strata): each follows its own Weyl sequence (fractional
# parts of offset + index * sqrt(prime)), so every option shows up at its share in any run of scenes.
STRATIFIED_CHOICES = (
    "kind",
    "ego_speed",
    "lead",
    "route_variant",
    "crossing",
    "cyclist",
    "construction",
    "single_frame",
    "ego_red",
    "movement",
    "lane_change",
)
_PRIMES = (2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37)
MAP_ID_RANGE = (10_000, 900_000)


def scene_token(seed: int, index: int) -> str:
    """Return the token of the index-th scene of a split: 16 hex digits from the seed and the index."""
    return short_hash(GENERATOR_VERSION, seed, index)


def _dice(seed: int, index: int, offsets: dict[str, float]) -> Dice:
    strata = {
        choice: (offsets[choice] + index * math.sqrt(prime)) % 1.0
        for choice, prime in zip(STRATIFIED_CHOICES, _PRIMES, strict=False)  # more primes than choices
    }
    return Dice(np.random.default_rng([seed, index]), strata)


def _draft(dice: Dice) -> SceneDraft:
    kind = dice.pick("kind", KINDS)
    first_id = int(dice.rng.integers(*MAP_ID_RANGE))
    if kind == "intersection":
        return intersection_scene(dice, first_id)
    return corridor_scene(dice, kind, first_id)


def synthesize_scene(seed: int, index: int) -> tuple[str, bytes, dict[str, object]]:
    """Return the token, the gzip file content and the generator's notes of one scene (a function of seed and index)."""
    offsets_rng = np.random.default_rng([seed, 1 << 20])
    offsets = dict(zip(STRATIFIED_CHOICES, offsets_rng.random(len(STRATIFIED_CHOICES)).tolist(), strict=True))
    dice = _dice(seed, index, offsets)
    token = scene_token(seed, index)
    draft = _draft(dice)
    document = scene_document(draft, token, dice)
    return token, encode_scene(document), {"index": index, "token": token, **draft.info}


def synthesize_split(
    out_dir: Path, n_scenes: int, seed: int, progress: Callable[[int], None] | None = None
) -> list[str]:
    """Write a synthetic split of n_scenes scenes to out_dir and return their tokens in generation order."""
    out_dir = Path(out_dir)
    scenes_dir = out_dir / "scenes"
    if scenes_dir.is_dir() and any(scenes_dir.iterdir()):
        raise FileExistsError(f"{scenes_dir}: not empty; synthesise into a new directory")
    scenes_dir.mkdir(parents=True, exist_ok=True)
    tokens, notes = [], []
    for index in range(n_scenes):
        token, content, note = synthesize_scene(seed, index)
        (scenes_dir / f"{token}.json.gz").write_bytes(content)
        tokens.append(token)
        notes.append(note)
        if progress is not None:
            progress(1)
    metadata = {
        "format": SPLIT_FORMAT,
        "name": out_dir.name,
        "seed": seed,
        "n": n_scenes,
        "generator_version": GENERATOR_VERSION,
        "scenes": notes,
    }
    (out_dir / "split.json").write_text(json.dumps(metadata, indent=1) + "\n")
    return tokens
