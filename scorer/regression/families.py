"""Trajectory families of the regression guard: baselines plus adversarial manoeuvres (ego frame, 8 poses)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from scorer.baselines import constant_velocity, human
from scorer.geometry import FloatArray
from scorer.scene import Scene

POSE_TIMES: FloatArray = np.arange(1, 9) * 0.5


def _smoothstep(t: FloatArray, duration: float) -> FloatArray:
    u = np.clip(t / duration, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _poses(x: FloatArray, y: FloatArray, heading: FloatArray | None = None) -> FloatArray:
    return np.stack([x, y, np.zeros_like(x) if heading is None else heading], axis=-1)


def stop(scene: Scene) -> FloatArray:
    """Return every pose at the origin."""
    return np.zeros((8, 3))


def hard_brake(scene: Scene) -> FloatArray:
    """Return a -7 m/s^2 brake along the heading to standstill."""
    speed = float(np.hypot(scene.current_frame.ego.vx, scene.current_frame.ego.vy))
    t = np.minimum(POSE_TIMES, speed / 7.0)
    return _poses(speed * t - 3.5 * t * t, np.zeros(8))


def reverse(scene: Scene) -> FloatArray:
    """Return a straight backwards drive."""
    return _poses(-1.5 * POSE_TIMES - 0.25 * POSE_TIMES**2, np.zeros(8))


def _lateral(offset: float) -> Callable[[Scene], FloatArray]:
    def swerve(scene: Scene) -> FloatArray:
        poses = human(scene).copy()
        poses[:, 1] += offset * _smoothstep(POSE_TIMES, 2.0)
        return poses

    return swerve


def zigzag(scene: Scene) -> FloatArray:
    """Return the human future with alternating +-1.5 m lateral and +-0.4 rad heading offsets."""
    poses = human(scene).copy()
    signs = np.where(np.arange(8) % 2 == 0, 1.0, -1.0)
    poses[:, 1] += 1.5 * signs
    poses[:, 2] += 0.4 * signs
    return poses


FAMILIES: dict[str, Callable[[Scene], FloatArray]] = {
    "constant_velocity": constant_velocity,
    "human": human,
    "stop": stop,
    "hard_brake": hard_brake,
    "reverse": reverse,
    "zigzag": zigzag,
    "swerve_left": _lateral(7.0),  # into the oncoming lane on right-hand-traffic roads
    "swerve_offroad": _lateral(-12.0),
}
