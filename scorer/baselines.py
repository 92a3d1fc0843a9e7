"""The two reference agents of the NAVSIM paper's Table 3, computed as the devkit's agents compute them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scorer.geometry import FloatArray, normalize_angle
from scorer.scene import Scene, iter_scenes
from scorer.submission import (
    INTERVAL_LENGTH_S,
    NUM_POSES,
    Submission,
    SubmissionMetadata,
    TwoStageSubmission,
)
from scorer.two_stage.split import load_two_stage_split

POSE_TIMES_S = np.arange(1, NUM_POSES + 1) * INTERVAL_LENGTH_S


def constant_velocity(scene: Scene) -> FloatArray:
    """Return NAVSIM's ConstantVelocityAgent: straight ahead at the current speed, as float32 poses."""
    ego = scene.current_frame.ego
    velocity = np.array([ego.vx, ego.vy], dtype=np.float32)
    speed = np.sqrt((velocity**2).sum(-1))
    poses = np.zeros((NUM_POSES, 3), dtype=np.float32)
    poses[:, 0] = POSE_TIMES_S * speed
    return poses.astype(np.float64)


def human(scene: Scene) -> FloatArray:
    """Return NAVSIM's HumanAgent: the recorded future ego poses in the current frame's ego frame."""
    start = scene.current_index
    frames = scene.frames[start : start + NUM_POSES + 1]
    poses = np.array([(f.ego.x, f.ego.y, f.ego.heading) for f in frames], dtype=np.float64)
    # As navsim's convert_absolute_to_relative_se2_array: subtract, rotate by -heading, wrap the angle.
    theta = -poses[0, 2]
    rotation = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    relative = poses[1:] - poses[:1]
    relative[:, :2] = relative[:, :2] @ rotation.T
    relative[:, 2] = normalize_angle(relative[:, 2])
    return relative


BASELINES = {"constant-velocity": constant_velocity, "human": human}


def baseline_submission(split_dir: Path, kind: str, method: str) -> Submission:
    """Return the single-seed submission of baseline `kind` ("constant-velocity" or "human") for a split."""
    agent = BASELINES[kind]
    predictions = {scene.token: agent(scene) for scene in iter_scenes(split_dir)}
    metadata = SubmissionMetadata(team_name="baseline", method=method)
    return Submission(metadata, (predictions,))


def two_stage_baseline_submission(split_dir: Path, kind: str, method: str) -> TwoStageSubmission:
    """Return the single-seed two-stage submission of baseline `kind` for a two-stage split: its predictions
    of every scene, each stage's tokens in the split's stage order."""
    predictions = baseline_submission(split_dir, kind, method)
    stages = load_two_stage_split(split_dir)
    first, second = (
        {token: predictions.seeds[0][token] for token in tokens}
        for tokens in (stages.stage_one_tokens, stages.stage_two_tokens)
    )
    return TwoStageSubmission(predictions.metadata, (first,), (second,))
