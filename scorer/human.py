"""v2's human penalty filter: the logged human, scored like a submission, forgives the agent where it fails
too (docs/engine.md, "v2.2: the human filter").

As `pdm_score` at tag v2.2 (with the fix of Issue #151): on original scenes (tokens of other than 17
characters), the human's logged future, 8 poses at 0.5 s, is simulated alone and scored without past states,
so its EP and HC are always 1. In every column where the human scores exactly 0, the agent's value becomes
1 (a human NC or DDC of 0.5 forgives nothing); the product of the multipliers and the weighted row are then
recomputed from the filtered columns, while EP keeps the normaliser of the unfiltered multipliers (before the
fix, v2.2-prefix, the score stays the agent's unfiltered one: `MetricVersion.human_filter_rescores`). The
human depends on the scene alone, so its result is computed once, with the metric cache.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from scorer.geometry import FloatArray, rear_axle_round_trip
from scorer.scene import Scene
from scorer.trajectory import global_to_relative
from scorer.versions import EPDMS_COLUMNS

SYNTHETIC_TOKEN_LENGTH = 17  # the devkit's test for a synthetic scene (`len(scenario.token) == 17`)
HUMAN_POSES = 8  # 4 s at the logs' 0.5 s interval
# The filtered columns: every result column of the scorer but the score (EC is joined per split, later).
FILTERED_COLUMNS = tuple(c for c in EPDMS_COLUMNS if c not in ("two_frame_extended_comfort", "score"))


def is_synthetic(token: str) -> bool:
    """Return whether v2 takes the token for a synthetic scene: no human, no filter, no EC pairing."""
    return len(token) == SYNTHETIC_TOKEN_LENGTH


def human_future_poses(scene: Scene) -> FloatArray:
    """Return the logged human's 8 future poses (8, 3) in the current ego frame, as the metric cache holds
    them (`_extract_ego_future_trajectory`): the rear axles of the current frame and the 8 after it, each
    after the EgoState round trip, made relative to the first with nuPlan's matrices."""
    frames = scene.frames[scene.current_index : scene.current_index + HUMAN_POSES + 1]
    poses = np.array([[frame.ego.x, frame.ego.y, frame.ego.heading] for frame in frames], dtype=np.float64)
    poses[:, 0], poses[:, 1] = rear_axle_round_trip(poses[:, 0], poses[:, 1], poses[:, 2])
    return global_to_relative(poses)[1:]


def filtered(agent: Mapping[str, float], human: Mapping[str, float]) -> tuple[dict[str, float], list[str]]:
    """Return the agent's columns after the filter, and the columns the filter set to 1."""
    overridden = [column for column in FILTERED_COLUMNS if human[column] == 0]
    return {column: 1.0 if column in overridden else agent[column] for column in agent}, overridden
