"""Driving-direction compliance (DDC) in {0, 0.5, 1} (docs/engine.md, "Metrics").

The off-route distance per step (centre displacement where the centre is on no on-route lane) is
summed over a window of 11 and the maximum is thresholded. v1.1 sums over time, as intended; v1.0's
code sums over the *proposal* axis (proposals p-10..p at the same time index; docs/engine.md,
"Metric versions"), which a version selects with `ScorerConfig.ddc_window_axis`. Both sums keep the
devkit's float order.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from scorer.geometry import FloatArray
from scorer.metrics.ego_areas import EgoArea
from scorer.metrics.ego_box import BoxPoint
from scorer.versions import ScorerConfig

PAIRWISE_BLOCK = 8  # numpy sums 8 or more contiguous values with 8 partial sums (pairwise summation)


def off_route_steps(
    points: FloatArray, areas: npt.NDArray[np.bool_], excluded: npt.NDArray[np.bool_] | None = None
) -> FloatArray:
    """Return the centre's per-step displacement (R, T) where it is off route (0 at index 0 and elsewhere),
    and 0 at the `excluded` steps (v2: centre inside an intersection)."""
    center = points[..., BoxPoint.CENTER, :]
    steps = np.zeros(center.shape[:2])
    steps[:, 1:] = np.linalg.norm(center[:, 1:] - center[:, :-1], axis=-1)
    steps[~areas[..., EgoArea.ONCOMING_TRAFFIC]] = 0.0
    if excluded is not None:
        steps[excluded] = 0.0
    return steps


def _time_windows(steps: FloatArray, horizon: int) -> FloatArray:
    """Return the trailing sums over time k - horizon .. k (..., T), each as numpy's `sum` of that slice.

    The devkit sums each slice with numpy: fewer than 8 values left to right, 8 and more as 8
    interleaved partial sums combined pairwise, then the rest left to right. Reproduced on gathered
    windows, zero-padded past each window's end (adding 0 changes nothing).
    """
    num_steps = steps.shape[-1]
    if horizon + 1 >= 2 * PAIRWISE_BLOCK:  # numpy would fold a second block into the partial sums
        return np.stack(
            [steps[..., max(0, k - horizon) : k + 1].sum(axis=-1) for k in range(num_steps)], axis=-1
        )
    ends = np.arange(num_steps)
    starts = np.maximum(0, ends - horizon)
    positions = starts[:, None] + np.arange(horizon + 1)
    windows = np.where(positions <= ends[:, None], steps[..., np.minimum(positions, num_steps - 1)], 0.0)
    columns = [windows[..., index] for index in range(horizon + 1)]
    left_to_right = columns[0]
    for column in columns[1:]:
        left_to_right = left_to_right + column
    if horizon + 1 < PAIRWISE_BLOCK:
        return left_to_right
    pairwise = ((columns[0] + columns[1]) + (columns[2] + columns[3])) + (
        (columns[4] + columns[5]) + (columns[6] + columns[7])
    )
    for column in columns[PAIRWISE_BLOCK:]:
        pairwise = pairwise + column
    return np.where(ends - starts + 1 >= PAIRWISE_BLOCK, pairwise, left_to_right)


def _proposal_windows(steps: FloatArray, horizon: int) -> FloatArray:
    # Python's `sum` over proposals max(0, p - horizon) .. p, left to right; leading zeros change nothing.
    windows = np.zeros_like(steps)
    num_proposals = steps.shape[1]
    for lag in range(min(horizon, num_proposals - 1), -1, -1):
        windows[:, lag:] = windows[:, lag:] + steps[:, : num_proposals - lag]
    return windows


def driving_direction_compliance(steps: FloatArray, config: ScorerConfig, step_s: float) -> FloatArray:
    """Return DDC (B, P) from the off-route steps (B, P, T) of B tokens, windowed along the config's axis."""
    horizon = int(config.driving_direction_horizon / step_s)
    window = _proposal_windows if config.ddc_window_axis == "proposal" else _time_windows
    worst = window(steps, horizon).max(axis=-1)
    return np.where(
        worst < config.driving_direction_compliance_threshold,
        1.0,
        np.where(worst < config.driving_direction_violation_threshold, 0.5, 0.0),
    )
