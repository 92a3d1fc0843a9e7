"""Bird's-eye pictures that explain one token's score (`scorer.explain`), drawn with matplotlib.

The map excerpt the metrics use (roadblocks, intersections, car parks, lanes and lane connectors), the
route's centreline, every object at the current time and, faintly, where it goes; the human's recorded
future, PDM-Closed's reference and the submitted trajectory as the simulator tracks them; the ego box at
the first infraction of each kind, with the object involved drawn in red at that time.

matplotlib is the engine's optional extra (`[plot]`): it is imported when a picture is drawn, never with the
module, so that the engine imports no plotting library.
"""

from __future__ import annotations

import io
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from scorer.cache import MetricCache
from scorer.drivable_map import CARPARK_AREA, INTERSECTION, LANE, LANE_CONNECTOR, ROADBLOCK
from scorer.explain import Explanation, Infraction
from scorer.geometry import FloatArray
from scorer.metrics.ego_box import ego_box_points, ego_corners
from scorer.observation import Observation
from scorer.trajectory import SCORING_INTERVAL_S, StateIndex
from scorer.versions import METRIC_LABELS, VERSIONS

if TYPE_CHECKING:
    from matplotlib.axes import Axes

MARGIN_M = 25.0
FUTURE_EVERY = 10  # draw objects' future boxes every 1 s
MAP_STYLE = {  # (face, edge, line width, z order)
    ROADBLOCK: ("#e4e7ee", "none", 0.0, 0),
    INTERSECTION: ("#d8dce6", "none", 0.0, 1),
    CARPARK_AREA: ("#e3efe4", "none", 0.0, 1),
    LANE: ("none", "#b9bfcc", 0.6, 2),
    LANE_CONNECTOR: ("none", "#c9cdd8", 0.5, 2),
}
OTHER_MAP_STYLE = ("none", "#dddddd", 0.4, 1)
COLORS = {"human": "#6b7385", "reference": "#2457c5", "agent": "#e07b00", "infraction": "#c42b1c"}


def render(explanation: Explanation, image_format: str = "png") -> bytes:
    """Return the picture of an explanation as PNG or SVG bytes.

    Each part is drawn by its own function, in the order below: artists of equal z order are drawn in the
    order they were added, and the legend lists its entries in that order too.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    figure = Figure(figsize=(8.5, 9.2), dpi=110, layout="constrained")
    axes = figure.add_subplot()
    # Metres from the ego's rear axle at the current time: map coordinates (UTM) make unreadable ticks.
    origin = explanation.agent_states[0, :2].copy()
    _draw_map(axes, explanation.cache, origin)
    _draw_objects(axes, explanation.cache.observation, origin)
    _draw_trajectories(axes, explanation, origin)
    for number, infraction in enumerate(explanation.infractions):
        _draw_infraction(axes, explanation, infraction, number, origin)
    _frame(axes, explanation, origin)
    buffer = io.BytesIO()
    figure.savefig(buffer, format=image_format)
    return buffer.getvalue()


def _box(axes: Axes, corners: FloatArray, **style: Any) -> None:
    from matplotlib.patches import Polygon

    axes.add_patch(Polygon(corners, closed=True, **style))


def _ego_box(states: FloatArray, step: int, origin: FloatArray) -> FloatArray:
    """Return the corners (4, 2) of the ego's box at time index `step`, relative to `origin`."""
    return ego_corners(ego_box_points(states[step])) - origin


def _draw_map(axes: Axes, cache: MetricCache, origin: FloatArray) -> None:
    """Draw the map excerpt the metrics use, each layer in its style, and the route's centreline."""
    for polygon, kind in zip(cache.drivable_map.polygons, cache.drivable_map.types, strict=True):
        face, edge, width, order = MAP_STYLE.get(kind, OTHER_MAP_STYLE)
        for part in getattr(polygon, "geoms", [polygon]):  # a multipolygon's parts one by one
            axes.fill(
                *(np.asarray(part.exterior.coords) - origin).T,
                facecolor=face,
                edgecolor=edge,
                linewidth=width,
                zorder=order,
            )
    axes.plot(
        *(cache.centerline[:, :2] - origin).T,
        color="#9aa3b5",
        linewidth=1.0,
        linestyle=(0, (4, 4)),
        zorder=3,
        label="route centreline",
    )


def _draw_objects(axes: Axes, observation: Observation, origin: FloatArray) -> None:
    """Draw every object present at the current time, and faintly where each one is every second after."""
    for index in range(len(observation.tokens)):
        for step in range(FUTURE_EVERY, observation.present.shape[0], FUTURE_EVERY):
            if observation.present[step, index]:
                _box(
                    axes,
                    observation.corners[step, index] - origin,
                    fill=False,
                    edgecolor="#8a93a6",
                    linewidth=0.4,
                    alpha=0.5,
                    zorder=4,
                )
        if observation.present[0, index]:
            _box(
                axes,
                observation.corners[0, index] - origin,
                facecolor="#ffffff",
                edgecolor="#4b5366",
                linewidth=0.9,
                zorder=5,
            )


def _draw_trajectories(axes: Axes, explanation: Explanation, origin: FloatArray) -> None:
    """Draw the human's recorded future, PDM-Closed's reference and the submission as the simulator tracks
    them, and the ego's box at the current time."""
    axes.plot(
        *(explanation.human_future[:, :2] - origin).T,
        color=COLORS["human"],
        linestyle="--",
        marker="o",
        markersize=3,
        linewidth=1.2,
        zorder=6,
        label="human (recorded)",
    )
    for name, states, label in (
        ("reference", explanation.reference_states, "PDM-Closed reference"),
        ("agent", explanation.agent_states, "submission (simulated)"),
    ):
        axes.plot(
            states[:, StateIndex.X] - origin[0],
            states[:, StateIndex.Y] - origin[1],
            color=COLORS[name],
            linewidth=2.0,
            zorder=7,
            label=label,
        )
    start = _ego_box(explanation.agent_states, 0, origin)
    _box(axes, start, facecolor="#ffd9a8", edgecolor=COLORS["agent"], linewidth=1.2, zorder=8)


def _draw_infraction(
    axes: Axes, explanation: Explanation, infraction: Infraction, number: int, origin: FloatArray
) -> None:
    """Draw the ego's box at an infraction, the object involved at that time in red, and a label; the
    `number`-th infraction's label sits higher, so that labels of nearby infractions do not overlap."""
    step = round(infraction.time_s / SCORING_INTERVAL_S)
    ego = _ego_box(explanation.agent_states, step, origin)
    _box(axes, ego, fill=False, edgecolor=COLORS["infraction"], linewidth=1.6, zorder=9)
    observation = explanation.cache.observation
    if infraction.object_index is not None and step < observation.present.shape[0]:
        _box(
            axes,
            observation.corners[step, infraction.object_index] - origin,
            facecolor="#f6c6c0",
            edgecolor=COLORS["infraction"],
            linewidth=1.6,
            zorder=9,
        )
    axes.annotate(
        _infraction_label(infraction),
        ego.mean(axis=0),
        xytext=(16, 16 + 22 * number),
        textcoords="offset points",
        color=COLORS["infraction"],
        fontsize=9,
        zorder=10,
        arrowprops={"arrowstyle": "-", "color": COLORS["infraction"], "linewidth": 0.8},
        bbox={"boxstyle": "round,pad=0.2", "facecolor": "white", "edgecolor": "none", "alpha": 0.85},
    )


def _infraction_label(infraction: Infraction) -> str:
    """Return an infraction's label: its kind, its time and the object involved, if any."""
    what = (
        f" with {(infraction.object_type or 'object').lower()} {infraction.object_token[:8]}"
        if infraction.object_token
        else ""
    )
    return f"{infraction.kind} at {infraction.time_s:.1f} s{what}"


def _frame(axes: Axes, explanation: Explanation, origin: FloatArray) -> None:
    """Set the view, the axis labels, the legend and the title (the token, its score and subscores)."""
    x_low, x_high, y_low, y_high = _extent(explanation, origin)
    axes.set_xlim(x_low, x_high)
    axes.set_ylim(y_low, y_high)
    axes.set_aspect("equal")
    axes.set_xlabel("x (m from the ego's start)")
    axes.set_ylabel("y (m from the ego's start)")
    axes.legend(loc="upper left", fontsize=8, framealpha=0.9)
    axes.set_title(_title(explanation), fontsize=10)


def _extent(explanation: Explanation, origin: FloatArray) -> tuple[float, float, float, float]:
    """Return the square view (x low, x high, y low, y high) around the three trajectories, with a margin."""
    points = (
        np.concatenate(
            [
                explanation.agent_states[:, :2],
                explanation.reference_states[:, :2],
                explanation.human_future[:, :2],
            ]
        )
        - origin
    )
    low, high = points.min(axis=0) - MARGIN_M, points.max(axis=0) + MARGIN_M
    half = max(high - low) / 2  # a square view: equal scale on both axes without distortion
    centre = (low + high) / 2
    return centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half


def _title(explanation: Explanation) -> str:
    """Return the title: the token and its score, and on a second line every subscore, in percent."""
    metrics = explanation.metrics
    subscores = "  ".join(  # an undefined value (v2.2's EC of a token drawn alone) is left out
        f"{METRIC_LABELS[column]} {100 * value:.1f}"
        for column, value in metrics.items()
        if column != "score" and not math.isnan(value)
    )
    score_label = VERSIONS[explanation.version].score_label
    score = f"{score_label} {explanation.version} {100 * metrics['score']:.1f}"
    return f"{explanation.token} · {score}\n{subscores}"
