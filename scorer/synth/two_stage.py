"""Synthetic two-stage splits: groups of NAVSIM's two-stage form (docs/scene-format.md, "Two-stage splits")
built from the synthetic scenes of `scorer.synth.split`, the same bytes for the same seed.

Group i rests on the one-stage split's scene i (its token kept: `orig`). The other scenes of the group are
that scene moved rigidly (every global point of its frames, objects and map shifted alike, its clock shifted
alike), so each is as consistent as the scene it comes from:

- `prev`, the frame 0.5 s before: moved back by the ego's velocity x 0.5 s;
- each synthetic pair's `now2`, starting 4 s later: moved so that its ego starts at the logged ego's pose
  4 s after `orig` plus a perturbation of a few decimetres (NAVSIM perturbs the synthetic starts about the
  logged path; the Gaussian weights, sigma^2 = 0.1 m^2, then tell the starts apart), and its `prev2` 0.5 s
  before it, as `prev` is to `orig`.

Headings are not turned: the roll-outs are not those of a simulator, but every token is a scene the engine
scores as it scores NAVSIM's, with the weights, groups and two-frame comfort of the two-stage aggregation.
That is what it is for: the regression goldens of the aggregation and the service's navhard-size benchmark.
"""

from __future__ import annotations

import copy
import gzip
import hashlib
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from scorer.synth.export import encode_scene
from scorer.synth.split import GENERATOR_VERSION, synthesize_scene
from scorer.two_stage.split import MAPPING_FILE, SPLIT_FORMAT, SPLIT_VERSION

TWO_STAGE_GENERATOR = f"{GENERATOR_VERSION}/two-stage/1"
PREVIOUS_FRAME_S = 0.5
STAGE_TWO_DELAY_S = 4.0
PERTURBATION_M = 0.4  # standard deviation of each synthetic start's offset from the logged pose, per axis
SYNTHETIC_TOKEN_LENGTH = 17  # NAVSIM's rule: a 17-character token is a synthetic scene


def _token(length: int, *parts: object) -> str:
    return hashlib.sha256("/".join(str(part) for part in (TWO_STAGE_GENERATOR, *parts)).encode()).hexdigest()[
        :length
    ]


def _moved(
    document: dict[str, Any], token: str, shift: tuple[float, float], delay_s: float
) -> dict[str, Any]:
    """Return the scene `document` moved by `shift` (m) and `delay_s` (s), as scene `token`."""
    dx, dy = shift
    moved = copy.deepcopy(document)
    moved["token"] = token
    current = moved["current_index"]
    for index, frame in enumerate(moved["frames"]):
        frame["token"] = token if index == current else _token(16, token, index)
        frame["timestamp_us"] += round(delay_s * 1e6)
        frame["ego"]["x"] += dx
        frame["ego"]["y"] += dy
        for item in frame["objects"]:
            item["box"][0] += dx
            item["box"][1] += dy
    for layer in moved["map"].values():
        for element in layer:
            for key in ("polygon", "baseline"):
                if key in element:
                    element[key] = [[x + dx, y + dy] for x, y in element[key]]
    return moved


def _back_half_a_second(document: dict[str, Any]) -> tuple[float, float]:
    """Return the shift that moves a scene's ego back by its velocity over 0.5 s (global frame)."""
    ego = document["frames"][document["current_index"]]["ego"]
    cos, sin = math.cos(ego["heading"]), math.sin(ego["heading"])
    return (
        -(ego["vx"] * cos - ego["vy"] * sin) * PREVIOUS_FRAME_S,
        -(ego["vx"] * sin + ego["vy"] * cos) * PREVIOUS_FRAME_S,
    )


def synthesize_two_stage_split(
    out_dir: Path, groups: int, pairs: int, seed: int, progress: Callable[[int], None] | None = None
) -> list[list[Any]]:
    """Write a two-stage split of `groups` groups, each with `pairs` synthetic pairs (2 + 2 x pairs scenes a
    group), to `out_dir` (`scenes/` and `two_stage.json`) and return its `reactive_all_mapping`."""
    scenes_dir = Path(out_dir) / "scenes"
    if scenes_dir.is_dir() and any(scenes_dir.iterdir()):
        raise FileExistsError(f"{scenes_dir}: not empty; synthesise into a new directory")
    scenes_dir.mkdir(parents=True, exist_ok=True)

    def write(document: dict[str, Any]) -> str:
        (scenes_dir / f"{document['token']}.json.gz").write_bytes(encode_scene(document))
        if progress is not None:
            progress(1)
        return str(document["token"])

    mapping: list[list[Any]] = []
    for index in range(groups):
        original, content, _ = synthesize_scene(seed, index)
        document = json.loads(gzip.decompress(content))
        frames, current = document["frames"], document["current_index"]
        later = frames[current + round(STAGE_TWO_DELAY_S / document["frame_interval_s"])]["ego"]
        ahead = (later["x"] - frames[current]["ego"]["x"], later["y"] - frames[current]["ego"]["y"])
        write(document)
        previous = write(
            _moved(
                document, _token(16, seed, index, "prev"), _back_half_a_second(document), -PREVIOUS_FRAME_S
            )
        )
        rng = np.random.default_rng([seed, index, 2])
        synthetic = []
        for pair in range(pairs):
            dx, dy = rng.normal(0.0, PERTURBATION_M, 2).tolist()
            now2 = _moved(
                document,
                _token(SYNTHETIC_TOKEN_LENGTH, seed, index, pair, "now2"),
                (ahead[0] + dx, ahead[1] + dy),
                STAGE_TWO_DELAY_S,
            )
            back = _back_half_a_second(now2)
            prev2 = _moved(
                now2, _token(SYNTHETIC_TOKEN_LENGTH, seed, index, pair, "prev2"), back, -PREVIOUS_FRAME_S
            )
            synthetic.append([write(now2), write(prev2)])
        mapping.append([original, previous, synthetic])
    document = {
        "format": SPLIT_FORMAT,
        "version": SPLIT_VERSION,
        "reactive_all_mapping": mapping,
        "generator": {"name": TWO_STAGE_GENERATOR, "seed": seed, "groups": groups, "pairs": pairs},
    }
    (Path(out_dir) / MAPPING_FILE).write_text(json.dumps(document, indent=1) + "\n")
    return mapping
