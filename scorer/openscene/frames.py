"""OpenScene frame dicts to scene-file frames, converted exactly as NAVSIM v1.x does.

The ego pose is the rear axle: (x, y) from `ego2global_translation`, heading = pyquaternion's yaw of
`ego2global_rotation`. Boxes and agent velocities are stored in the ego frame and are rotated by that
yaw and shifted by the rear axle of a nuPlan EgoState (which went through the centre and back;
docs/engine.md, "Conventions: the rear-axle round trip").
Every numpy arctan2 of the devkit here (pyquaternion's yaw, PDM's `normalize_angle`) ran on the
AVX-512 machine that made the official results, hence `geometry.arctan2_avx512`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from scorer.geometry import FloatArray, arctan2_avx512, normalize_angle, rear_axle_round_trip
from scorer.scene import AGENT_CATEGORIES, CATEGORIES

NUM_HISTORY_FRAMES = 4  # NAVSIM's SceneFilter: 3 past frames plus the current one
NUM_FUTURE_FRAMES = 10
CURRENT_INDEX = NUM_HISTORY_FRAMES - 1
NUM_FRAMES = NUM_HISTORY_FRAMES + NUM_FUTURE_FRAMES
FRAME_INTERVAL_S = 0.5
FRAME_INTERVAL_US = 500_000  # NavSimScenario's time beyond the frames: last + k x TimeDuration.from_s(0.5)
OBSERVED_FUTURE_FRAMES = 8  # what v2 observes (4 s, `observation_frames` in versions.py)
UNIT_QUATERNION_TOLERANCE = 1e-14  # pyquaternion's `is_unit` tolerance on the sum of squares
ANNOTATION_KEYS = ("gt_boxes", "gt_names", "gt_velocity_3d", "instance_tokens", "track_tokens")


class FrameError(ValueError):
    """A log frame cannot be converted; the message names the frame token and the key."""


@dataclass(frozen=True)
class EgoPose:
    """Global rear-axle pose of a log frame."""

    x: float
    y: float
    heading: float


def quaternion_yaw(wxyz: Sequence[float] | FloatArray) -> float:
    """Return pyquaternion's `yaw_pitch_roll[0]` of a [w, x, y, z] quaternion, normalised as pyquaternion does."""
    q = np.asarray([float(value) for value in wxyz])
    sum_of_squares = np.dot(q, q)
    if not abs(1.0 - sum_of_squares) < UNIT_QUATERNION_TOLERANCE:
        norm = math.sqrt(sum_of_squares)
        if norm > 0:
            q = q / norm
    return float(arctan2_avx512(2 * (q[0] * q[3] - q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2)))


def ego_pose(frame: Mapping[str, Any]) -> EgoPose:
    """Return the global rear-axle pose NAVSIM builds for a log frame (`Scene._build_ego_status`)."""
    translation = _numbers(frame, "ego2global_translation", 3)
    return EgoPose(
        float(translation[0]),
        float(translation[1]),
        quaternion_yaw(_numbers(frame, "ego2global_rotation", 4)),
    )


def boxes_to_global(local_boxes: FloatArray, pose: EgoPose) -> FloatArray:
    """Return (n, 7) boxes in the global frame from ego-frame boxes (`gt_boxes_oriented_box`)."""
    rear_x, rear_y = rear_axle_round_trip(pose.x, pose.y, pose.heading)
    sin, cos = np.sin(pose.heading), np.cos(pose.heading)
    x, y = local_boxes[:, 0], local_boxes[:, 1]
    boxes = local_boxes.copy()
    boxes[:, 0] = (x * cos - y * sin) + rear_x
    boxes[:, 1] = (x * sin + y * cos) + rear_y
    # `rotate_state_se2` wraps the summed heading, then the caller wraps it once more.
    boxes[:, 6] = normalize_angle(normalize_angle(local_boxes[:, 6] + pose.heading))
    return boxes


def velocities_to_global(local_velocities: FloatArray, pose: EgoPose) -> FloatArray:
    """Return (n, 2) global velocities from `gt_velocity_3d` (treated as ego frame, as NAVSIM does)."""
    sin, cos = np.sin(pose.heading), np.cos(pose.heading)
    vx, vy = local_velocities[:, 0], local_velocities[:, 1]
    return np.stack([vx * cos - vy * sin, vx * sin + vy * cos], axis=-1).reshape(-1, 2)


def vehicle_centres(objects: Sequence[Mapping[str, Any]]) -> list[tuple[float, float]]:
    """Return the box centres of a scene-file frame's vehicles (what the reactive traffic places on lanes)."""
    return [(obj["box"][0], obj["box"][1]) for obj in objects if obj["category"] == "vehicle"]


def driving_command(frame: Mapping[str, Any]) -> list[int] | None:
    """Return the stored one-hot [left, straight, right, unknown] command, or None when absent or not one-hot."""
    raw = frame.get("driving_command")
    if raw is None:
        return None
    try:
        values = [int(value) for value in np.asarray(raw).reshape(-1)]
    except (TypeError, ValueError):
        return None
    if len(values) != 4 or any(value not in (0, 1) for value in values) or sum(values) != 1:
        return None
    return values


def convert_frame(frame: Mapping[str, Any]) -> dict[str, Any]:
    """Return the scene-file frame of a log frame; `driving_command` is the stored one or None."""
    token = _token(frame)
    try:
        return _convert(frame, token)
    except FrameError:
        raise
    except (TypeError, ValueError, KeyError, IndexError) as error:
        raise FrameError(f"frame {token}: malformed value ({type(error).__name__}: {error})") from None


def _convert(frame: Mapping[str, Any], token: str) -> dict[str, Any]:
    pose = ego_pose(frame)
    return {
        "token": token,
        "timestamp_us": _integer(frame, "timestamp"),
        "ego": {
            "x": pose.x,
            "y": pose.y,
            "heading": pose.heading,
            **dict(
                zip(
                    ("vx", "vy", "ax", "ay"), map(float, _numbers(frame, "ego_dynamic_state", 4)), strict=True
                )
            ),
        },
        "driving_command": driving_command(frame),
        "objects": _objects(frame, token, pose),
        "traffic_lights": [
            [str(int(lane_connector)), bool(is_red)]
            for lane_connector, is_red in _get(frame, "traffic_lights")
        ],
        "route_roadblocks": route_roadblocks(frame),
    }


def route_roadblocks(frame: Mapping[str, Any]) -> list[str]:
    """Return the frame's route roadblock ids as strings, in route order."""
    return [str(roadblock) for roadblock in _get(frame, "roadblock_ids")]


def scene_windows(
    frames: Sequence[Mapping[str, Any]], frame_interval: int, future_frames: int = NUM_FUTURE_FRAMES
) -> Iterator[tuple[str, int]]:
    """Yield (token, start) of every full window of 4 + `future_frames` frames, cut as NAVSIM's
    `filter_scenes` does (its SceneFilter's `num_future_frames`: 10 for navtest, 8 for navhard)."""
    for start in range(0, len(frames), frame_interval):
        if start + NUM_HISTORY_FRAMES + future_frames <= len(frames):
            yield _token(frames[start + CURRENT_INDEX]), start


def window_problem(
    frames: Sequence[Mapping[str, Any]],
    index: int,
    frame_interval: int,
    future_frames: int = NUM_FUTURE_FRAMES,
) -> str | None:
    """Return why the frame at `index` is no scene token under `frame_interval`, or None if it is one."""
    if index < CURRENT_INDEX:
        return f"only {index} frame(s) before it in the log; a scene needs {CURRENT_INDEX}"
    if index + future_frames >= len(frames):
        return f"only {len(frames) - index - 1} frame(s) after it in the log; a scene needs {future_frames}"
    if (index - CURRENT_INDEX) % frame_interval:
        return f"not at a window position for frame interval {frame_interval}"
    return None


def held_frame(frame: Mapping[str, Any], steps: int) -> dict[str, Any]:
    """Return a scene-file frame held `steps` frame intervals later (same ego, objects and lights): how a scene
    whose source ends after the 8 future frames v2 observes fills the format's 10."""
    return {
        **frame,
        "token": f"{frame['token']}+{steps}",
        "timestamp_us": frame["timestamp_us"] + steps * FRAME_INTERVAL_US,
    }


def padded_future(future: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], tuple[str, ...]]:
    """Return future frames held to the format's 10 and, if any was added, the warning saying so."""
    if len(future) >= NUM_FUTURE_FRAMES:
        return future, ()
    warning = (
        f"{len(future)} future frames, the last held to +{NUM_FUTURE_FRAMES} "
        f"(v2 observes {OBSERVED_FUTURE_FRAMES}; only v1.x versions would read the held ones)"
    )
    held = [held_frame(future[-1], step) for step in range(1, NUM_FUTURE_FRAMES - len(future) + 1)]
    return future + held, (warning,)


def _objects(frame: Mapping[str, Any], token: str, pose: EgoPose) -> list[dict[str, Any]]:
    annotations = _get(frame, "anns")
    if not isinstance(annotations, Mapping):
        raise FrameError(f"frame {token}: anns: expected a dict")
    lengths = {key: len(_get(annotations, key, f"anns.{key}", token)) for key in ANNOTATION_KEYS}
    if len(set(lengths.values())) != 1:
        raise FrameError(f"frame {token}: anns: annotation lists differ in length {lengths}")
    count = lengths["gt_boxes"]
    try:
        local_boxes = np.asarray(annotations["gt_boxes"], dtype=np.float64).reshape(count, 7)
        local_velocities = np.asarray(annotations["gt_velocity_3d"], dtype=np.float64).reshape(count, 3)
    except ValueError:
        raise FrameError(f"frame {token}: anns: expected gt_boxes (n, 7) and gt_velocity_3d (n, 3)") from None
    categories = [str(name) for name in annotations["gt_names"]]
    unknown = sorted(set(categories) - set(CATEGORIES))
    if unknown:
        raise FrameError(
            f"frame {token}: anns.gt_names: unknown class(es) {unknown}; expected one of {CATEGORIES}"
        )
    return global_objects(annotations["track_tokens"], categories, local_boxes, local_velocities, pose)


def global_objects(
    tracks: Sequence[Any],
    categories: Sequence[str],
    local_boxes: FloatArray,
    local_velocities: FloatArray,
    pose: EgoPose,
) -> list[dict[str, Any]]:
    """Return scene-file objects of ego-frame annotations (boxes (n, 7), velocities (n, >= 2)) seen from
    `pose`: global boxes, global velocities for agents and zero for static objects."""
    boxes = boxes_to_global(local_boxes, pose)
    is_agent = np.isin(categories, AGENT_CATEGORIES)
    velocities = np.where(is_agent[:, None], velocities_to_global(local_velocities, pose), 0.0)
    return [
        {"track": str(track), "category": category, "box": box.tolist(), "velocity": velocity.tolist()}
        for track, category, box, velocity in zip(tracks, categories, boxes, velocities, strict=True)
    ]


def _token(frame: Mapping[str, Any]) -> str:
    token = frame.get("token")
    if not isinstance(token, str) or not token:
        raise FrameError(f"a frame has no token (got {token!r})")
    return token


def _get(obj: Mapping[str, Any], key: str, where: str | None = None, token: str | None = None) -> Any:
    if key not in obj:
        raise FrameError(f"frame {token or obj.get('token')}: {where or key}: missing key")
    return obj[key]


def _numbers(frame: Mapping[str, Any], key: str, size: int) -> FloatArray:
    try:
        values = np.asarray(_get(frame, key), dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise FrameError(f"frame {frame.get('token')}: {key}: expected {size} numbers") from None
    if len(values) < size or not np.all(np.isfinite(values[:size])):
        raise FrameError(
            f"frame {frame.get('token')}: {key}: expected {size} finite numbers, got {values.tolist()}"
        )
    return values[:size]


def _integer(frame: Mapping[str, Any], key: str) -> int:
    value = _get(frame, key)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise FrameError(f"frame {frame.get('token')}: {key}: expected an integer, got {value!r}")
    return int(value)
