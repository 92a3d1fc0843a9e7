"""The synthetic starts around a stage-one token's submitted endpoint, with their weights (for the pictures).

A stage-one token's stage two is the set of synthetic scenes its mapping entry pairs with it (`now2` for the
original frame, `prev2` for the frame 0.5 s before it). Each one starts from a perturbed ego state 4 s later,
and weighs by how close that start lies to where the submitted plan ends (`scorer.two_stage.weights`): the
drill-down picture draws those starts with their weights, computed exactly as the aggregation computes them,
and says of a synthetic token which stage-one token weighs it.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from scorer.geometry import FloatArray
from scorer.scene import scene_paths
from scorer.two_stage.score import start_pose
from scorer.two_stage.split import MAPPING_FILE, StageGroup, read_two_stage_split
from scorer.two_stage.weights import WeightSets, global_endpoints, pseudo_closed_loop_weights


@dataclass(frozen=True, eq=False)
class SyntheticStarts:
    """The stage-two scenes weighted against one stage-one token's submitted endpoint."""

    tokens: tuple[str, ...]  # the synthetic tokens, in mapping order
    start_poses: FloatArray  # (n, 3) each one's ego rear axle at its start: x, y, heading (global frame)
    endpoint: FloatArray  # (2,) the stage-one token's last submitted pose, in the global frame
    weights: WeightSets


class StageTwoPlace(NamedTuple):
    """Where a synthetic token sits in its split's stage mapping."""

    stage_one: str  # the stage-one token whose endpoint weighs it
    position: int  # its place among that token's synthetic starts, from 0
    starts: int  # how many synthetic starts that token has


def _groups(split_dir: Path) -> tuple[StageGroup, ...]:
    """Return the groups of the stage mapping of the split at `split_dir` (none without a mapping), read
    without listing its scenes: the directory may hold only those a picture needs (a stored split's copy)."""
    path = Path(split_dir) / MAPPING_FILE
    return (read_two_stage_split(path).groups or ()) if path.is_file() else ()


def successors(groups: Iterable[StageGroup], token: str) -> tuple[str, ...]:
    """Return the synthetic tokens stage-one `token` weighs (its entry's now2 for the original frame, prev2
    for the previous one); none where `token` is no entry's original or previous frame."""
    for group in groups:
        if token == group.original:
            return group.now_tokens
        if token == group.previous:
            return group.previous_tokens
    return ()


def stage_two_place(split_dir: Path, token: str) -> StageTwoPlace | None:
    """Return the place of synthetic `token` in the stage mapping of the split at `split_dir`; None where the
    split has no mapping or the mapping has no such stage-two token."""
    for group in _groups(split_dir):
        for stage_one, successors in (
            (group.original, group.now_tokens),
            (group.previous, group.previous_tokens),
        ):
            if token in successors:
                return StageTwoPlace(stage_one, successors.index(token), len(successors))
    return None


def synthetic_starts(
    split_dir: Path, token: str, poses: FloatArray, token_start: FloatArray
) -> SyntheticStarts | None:
    """Return the synthetic starts of stage-one `token` of the two-stage split at `split_dir`, weighted against
    its submitted `poses` (8, 3) from its ego rear axle `token_start` (x, y, heading); None where the split has
    no stage mapping or `token` is no mapping entry's original or previous frame."""
    weighed = successors(_groups(split_dir), token)
    if not weighed:
        return None
    paths = scene_paths(split_dir)
    starts = np.array([start_pose(paths.get(successor)) for successor in weighed], dtype=np.float64)
    endpoint = global_endpoints(np.asarray(poses, dtype=np.float64)[None], np.asarray(token_start)[None, :3])
    weights = pseudo_closed_loop_weights(endpoint, starts[:, :2], [np.arange(len(weighed))])
    return SyntheticStarts(tokens=weighed, start_poses=starts, endpoint=endpoint[0], weights=weights)
