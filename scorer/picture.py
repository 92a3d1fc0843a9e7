"""Bird's-eye pictures that explain one token's score (`scorer.explain`), drawn with matplotlib.

What the metrics read, told apart so that a reader can check each infraction by eye: the drivable layers the
DAC counts (roadblocks, intersections, car parks: filled) apart from the lanes and lane connectors (outlined:
they decide oncoming traffic, not drivability) and the non-drivable walkways and crosswalks; lanes under a red
light; every object at the current time and where it goes (under reactive traffic, the vehicles as they
reacted to the submission); the human's recorded future, PDM-Closed's reference and the submitted trajectory
as the simulator tracks them; the ego box at the first infraction of each kind, numbered, each kind in its own
colour, with the object or light involved; on a two-stage split's stage-one token, the synthetic starts of
its stage two with their weights. Every mark drawn has a legend entry.

Two layouts: "wide" (1100 x 660 px, the legend beside the map) fits a 1366 x 768 window; "narrow" (360 px wide,
at most 740 tall: the infractions, then the legend, under a map cropped around the ego's path, and the picture
cut under them) fits a phone. Equal inputs give equal bytes (no
date in an SVG, fixed SVG ids), so that rendered pictures can be cached and compared.

matplotlib is the engine's optional extra (`[plot]`): it is imported when a picture is drawn, never with the
module, so that the engine imports no plotting library.
"""

from __future__ import annotations

import io
import math
import textwrap
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from scorer.drivable_map import CARPARK_AREA, INTERSECTION, LANE, LANE_CONNECTOR, ROADBLOCK
from scorer.explain import INFRACTION_COLUMNS, Explanation, Infraction
from scorer.geometry import FloatArray
from scorer.metrics.ego_box import ego_box_points, ego_corners
from scorer.trajectory import SCORING_INTERVAL_S, STATE_SIZE, StateIndex
from scorer.versions import METRIC_LABELS, VERSIONS, get_version

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.transforms import Bbox

LayoutName = Literal["wide", "narrow"]
DPI = 100
FUTURE_EVERY = 10  # draw objects' future boxes every 1 s
VEHICLE = "VEHICLE"


@dataclass(frozen=True)
class Layout:
    """Where the title, the map and the legend sit, in figure fractions (left, bottom, width, height).

    The title comes first, at `title_at`, and its height decides the rest: beside the map ("wide"), the
    legend starts under it; stacked ("narrow"), the map starts under it and the legend under the map.
    """

    size_in: tuple[float, float]
    title_at: tuple[float, float]
    map_box: tuple[float, float, float, float]  # stacked: the bottom is where the title leaves room
    legend_x: tuple[float, float]  # left, width
    stacked: bool
    legend_columns: int
    title_width: int  # characters per line of the subscores
    font_pt: float
    margin_m: float  # around what the view must hold
    whole_view: bool  # the view holds the human's and the reference's paths too, not only the submission's


LAYOUTS: dict[str, Layout] = {
    "wide": Layout(
        size_in=(11.0, 6.6),
        title_at=(0.62, 0.975),
        map_box=(0.06, 0.08, 0.53, 0.88),
        legend_x=(0.615, 0.38),
        stacked=False,
        legend_columns=1,
        title_width=58,
        font_pt=9.5,
        margin_m=12.0,
        whole_view=True,
    ),
    "narrow": Layout(
        size_in=(3.6, 7.4),
        title_at=(0.03, 0.995),
        map_box=(0.14, 0.0, 0.84, 0.409),
        legend_x=(0.0, 1.0),
        stacked=True,
        legend_columns=2,
        title_width=50,
        font_pt=8.0,
        margin_m=6.0,
        whole_view=False,
    ),
}
GAP = 0.015  # between the title and what follows it, in figure fractions
BOTTOM_PAD_PX = 8  # under the last legend of a cropped (stacked) picture

# Drivable layers (DAC counts a corner inside one of them): filled. Lanes: outlined over them.
MAP_STYLE = {  # layer -> (legend label, face, edge, line width, z order)
    ROADBLOCK: ("drivable: roadblock", "#d3dae8", "none", 0.0, 1),
    INTERSECTION: ("drivable: intersection", "#c2cce2", "none", 0.0, 1),
    CARPARK_AREA: ("drivable: car park", "#cfe5d2", "none", 0.0, 1),
    LANE: ("lane (outline)", "none", "#8d96aa", 0.6, 3),
    LANE_CONNECTOR: ("lane (outline)", "none", "#8d96aa", 0.6, 3),
}
NON_DRIVABLE_STYLE = {  # layer -> (legend label, face, edge, hatch, z order)
    "walkway": ("walkway (not drivable)", "#efe3c4", "#c9b88f", None, 0),
    "crosswalk": ("crosswalk (not drivable)", "none", "#a89d82", "////", 2),
}
OFF_MAP_COLOR = "#ffffff"
COLORS = {
    "human": "#5f6778",
    "reference": "#2457c5",
    "agent": "#e07b00",
    "object": "#3b4252",
    "future": "#9aa2b1",
    "simulated": "#1f8fa0",
    "red light": "#f2a0a0",
    "start": "#222222",
}
INFRACTION_COLORS = {
    "collision": "#d7191c",
    "time to collision": "#e7298a",
    "off the drivable area": "#7b3294",
    "oncoming traffic": "#1a9641",
    "red light": "#8c510a",
    "lane keeping": "#b8860b",
}


def render(explanation: Explanation, image_format: str = "png", layout: LayoutName = "wide") -> bytes:
    """Return the picture of an explanation as PNG or SVG bytes, in the given layout.

    Each part is drawn by its own function; each returns its legend entries, listed in drawing order.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    shape = LAYOUTS[layout]
    with matplotlib.rc_context(
        {"font.size": shape.font_pt, "svg.hashsalt": "navsim-lb", "hatch.linewidth": 0.6}
    ):
        figure = Figure(figsize=shape.size_in, dpi=DPI)
        FigureCanvasAgg(figure)  # the layout measures text with its renderer
        axes, legend_axes = _place(figure, explanation, shape)
        # Metres from the ego's rear axle at the current time: map coordinates (UTM) make unreadable ticks.
        origin = explanation.agent_states[0, :2].copy()
        entries = [
            *_draw_map(axes, explanation, origin),
            *_draw_objects(axes, explanation, origin),
            *_draw_trajectories(axes, explanation, origin),
            *_draw_synthetic_starts(axes, explanation, origin),
        ]
        infractions = [
            _draw_infraction(axes, explanation, infraction, number, origin)
            for number, infraction in enumerate(explanation.infractions, 1)
        ]
        content_bottom = _frame(axes, legend_axes, explanation, origin, shape, entries, infractions)
        buffer = io.BytesIO()
        figure.savefig(
            buffer,
            format=image_format,
            metadata={"Date": None} if image_format == "svg" else None,
            bbox_inches=_cropped(shape, content_bottom),
        )
    return buffer.getvalue()


def _cropped(shape: Layout, content_bottom: float) -> Bbox | None:
    """Return the part of a stacked figure to save: its whole width, down to its content (a phone's picture
    with few infractions has no blank tail to scroll past), or None (all of it) for the wide layout."""
    from matplotlib.transforms import Bbox

    if not shape.stacked:
        return None
    width, height = shape.size_in
    bottom = max(0.0, math.floor(content_bottom - BOTTOM_PAD_PX)) / DPI  # whole pixels: byte-stable
    return Bbox([[0.0, bottom], [width, height]])


def _place(figure: Figure, explanation: Explanation, shape: Layout) -> tuple[Axes, Axes]:
    """Write the title and return the map's axes and the legend's, placed after the title's measured height."""
    renderer = figure.canvas.get_renderer()  # type: ignore[attr-defined]
    title = figure.text(
        *shape.title_at, _title(explanation, shape.title_width), va="top", ha="left", linespacing=1.35
    )
    below_title = figure.transFigure.inverted().transform((0, title.get_window_extent(renderer).y0))[1]
    left, bottom, width, height = shape.map_box
    if shape.stacked:
        bottom = below_title - GAP - height
    axes = figure.add_axes((left, bottom, width, height))
    axes.set_facecolor(OFF_MAP_COLOR)
    # Under a stacked map, room for its ticks and axis label.
    legend_top = bottom - 0.075 if shape.stacked else below_title - GAP
    legend_axes = figure.add_axes((shape.legend_x[0], 0.005, shape.legend_x[1], legend_top - 0.005))
    return axes, legend_axes


def _box(axes: Axes, corners: FloatArray, **style: Any) -> Artist:
    """Draw a closed polygon in data coordinates. As an artist, not a patch: the view is set at the end, so
    the axes need not widen their data limits patch by patch (two thirds of a picture's time otherwise)."""
    from matplotlib.patches import Polygon

    return axes.add_artist(Polygon(corners, closed=True, **style))


def _ego_box(states: FloatArray, step: int, origin: FloatArray) -> FloatArray:
    """Return the corners (4, 2) of the ego's box at time index `step`, relative to `origin`."""
    return ego_corners(ego_box_points(states[step])) - origin


def _fill(axes: Axes, polygon: Any, origin: FloatArray, **style: Any) -> Artist:
    """Draw a map polygon (a multipolygon part by part) relative to `origin`; return its first patch."""
    parts = getattr(polygon, "geoms", [polygon])
    patches = [_box(axes, np.asarray(part.exterior.coords)[:, :2] - origin, **style) for part in parts]
    return patches[0]


def _draw_map(axes: Axes, explanation: Explanation, origin: FloatArray) -> list[Artist]:
    """Draw the map excerpt: non-drivable walkways under the drivable layers, lanes outlined over them,
    crosswalks hatched over the road, lanes under a red light, and the route's centreline."""
    entries: dict[str, Artist] = {}
    for layer, polygon in explanation.non_drivable:
        label, face, edge, hatch, order = NON_DRIVABLE_STYLE[layer]
        patch = _fill(
            axes,
            polygon,
            origin,
            facecolor=face,
            edgecolor=edge,
            hatch=hatch,
            linewidth=0.5,
            zorder=order,
            label=label,
        )
        entries.setdefault(label, patch)
    drivable_map = explanation.cache.drivable_map
    for polygon, kind in zip(drivable_map.polygons, drivable_map.types, strict=True):
        label, face, edge, width, order = MAP_STYLE.get(kind, ("other map layer", "none", "#dddddd", 0.4, 1))
        patch = _fill(
            axes, polygon, origin, facecolor=face, edgecolor=edge, linewidth=width, zorder=order, label=label
        )
        entries.setdefault(label, patch)
    lights = explanation.observation.red_lights
    if lights is not None:
        for polygon in lights.polygons[lights.present.any(axis=0)]:
            patch = _fill(
                axes,
                polygon,
                origin,
                facecolor=COLORS["red light"],
                edgecolor="#d05050",
                linewidth=0.6,
                zorder=3,
                label="lane under a red light",
            )
            entries.setdefault("lane under a red light", patch)
    (route,) = axes.plot(
        *(explanation.cache.centerline[:, :2] - origin).T,
        color="#7d869a",
        linewidth=1.0,
        linestyle=(0, (4, 4)),
        zorder=4,
        label="route centreline",
    )
    listed = [
        *(label for label, *_ in MAP_STYLE.values()),
        *(label for label, *_ in NON_DRIVABLE_STYLE.values()),
        "other map layer",
        "lane under a red light",
    ]
    return [entries[label] for label in dict.fromkeys(listed) if label in entries] + [route]


def _draw_objects(axes: Axes, explanation: Explanation, origin: FloatArray) -> list[Artist]:
    """Draw every object present at the current time, and every second after where each one is: under
    reactive traffic, the vehicles as simulated (they react to the submission), in their own colour."""
    from matplotlib.patches import Patch

    observation = explanation.observation
    reactive = get_version(explanation.version).reactive_traffic is not None
    simulated = [reactive and kind == VEHICLE for kind in observation.object_types]
    entries: list[Artist] = []
    for index in range(len(observation.tokens)):
        for step in range(FUTURE_EVERY, observation.present.shape[0], FUTURE_EVERY):
            if observation.present[step, index]:
                style = (
                    {"edgecolor": COLORS["simulated"], "linewidth": 0.8, "linestyle": (0, (3, 2))}
                    if simulated[index]
                    else {"edgecolor": COLORS["future"], "linewidth": 0.5, "alpha": 0.8}
                )
                _box(axes, observation.corners[step, index] - origin, fill=False, zorder=5, **style)
        if observation.present[0, index]:
            _box(
                axes,
                observation.corners[0, index] - origin,
                facecolor="#ffffff",
                edgecolor=COLORS["object"],
                linewidth=0.9,
                zorder=6,
            )
    entries.append(Patch(facecolor="#ffffff", edgecolor=COLORS["object"], label="object now"))
    if any(not flag for flag in simulated):
        ahead = "logged, every 1 s"
        entries.append(Patch(fill=False, edgecolor=COLORS["future"], label=ahead))
    if any(simulated):
        entries.append(
            Patch(
                fill=False,
                edgecolor=COLORS["simulated"],
                linestyle=(0, (3, 2)),
                label="simulated, every 1 s",
            )
        )
    return entries


def _draw_trajectories(axes: Axes, explanation: Explanation, origin: FloatArray) -> list[Artist]:
    """Draw the human's recorded future, PDM-Closed's reference and the submission as the simulator tracks
    them, and the ego's box at the current time."""
    (human,) = axes.plot(
        *(explanation.human_future[:, :2] - origin).T,
        color=COLORS["human"],
        linestyle="--",
        marker="o",
        markersize=3,
        linewidth=1.2,
        zorder=7,
        label="human (recorded)",
    )
    lines = [human]
    for name, states, label in (
        ("reference", explanation.reference_states, "PDM-Closed reference"),
        ("agent", explanation.agent_states, "you (simulated)"),
    ):
        (line,) = axes.plot(
            states[:, StateIndex.X] - origin[0],
            states[:, StateIndex.Y] - origin[1],
            color=COLORS[name],
            linewidth=2.0,
            zorder=8,
            label=label,
        )
        lines.append(line)
    start = _ego_box(explanation.agent_states, 0, origin)
    ego = _box(
        axes, start, facecolor="#ffd9a8", edgecolor=COLORS["agent"], linewidth=1.2, zorder=9, label="ego now"
    )
    return [*lines, ego]


def _draw_synthetic_starts(axes: Axes, explanation: Explanation, origin: FloatArray) -> list[Artist]:
    """Draw a stage-one token's synthetic starts (the ego's box at each stage-two scene's start), each with its
    weight beside it, and the submitted endpoint they are weighted against."""
    starts = explanation.synthetic_starts
    if starts is None:
        return []
    states = np.zeros((len(starts.tokens), STATE_SIZE))
    states[:, [StateIndex.X, StateIndex.Y, StateIndex.HEADING]] = starts.start_poses
    boxes = ego_corners(ego_box_points(states)) - origin
    box = None
    count = len(boxes)
    for index, (corners, weight) in enumerate(zip(boxes, starts.weights.weight, strict=True)):
        box = _box(
            axes,
            corners,
            fill=False,
            edgecolor=COLORS["start"],
            linewidth=0.9,
            linestyle=(0, (2, 1.5)),
            zorder=10,
            label="synthetic start, weight",
        )
        # The starts lie within a few metres of each other: their weights fan out, each tied to its box.
        angle = math.radians(-90 + 360 * index / count)
        axes.annotate(
            f"{weight:.2f}" if weight >= 0.005 else "<0.01",
            corners.mean(axis=0),
            xytext=(34 * math.cos(angle), 34 * math.sin(angle)),
            textcoords="offset points",
            ha="center",
            va="center",
            fontsize="small",
            fontweight="bold",
            color=COLORS["start"],
            zorder=12,
            bbox={
                "boxstyle": "round,pad=0.15",
                "facecolor": "white",
                "edgecolor": COLORS["start"],
                "linewidth": 0.5,
            },
            arrowprops={
                "arrowstyle": "-",
                "color": COLORS["start"],
                "linewidth": 0.6,
                "shrinkA": 0,
                "shrinkB": 0,
            },
        )
    (endpoint,) = axes.plot(
        *(starts.endpoint - origin),
        marker="*",
        markersize=11,
        markerfacecolor=COLORS["agent"],
        markeredgecolor="#000000",
        linestyle="none",
        zorder=11,
        label="your endpoint (4 s)",
    )
    return [box, endpoint] if box is not None else [endpoint]


def _draw_infraction(
    axes: Axes, explanation: Explanation, infraction: Infraction, number: int, origin: FloatArray
) -> Artist:
    """Draw the ego's box at an infraction in its kind's colour with its number, the object or red light
    involved in that colour too; return its legend entry."""
    from matplotlib.patches import Patch

    color = INFRACTION_COLORS[infraction.kind]
    step = round(infraction.time_s / SCORING_INTERVAL_S)
    ego = _ego_box(explanation.agent_states, step, origin)
    _box(axes, ego, fill=False, edgecolor=color, linewidth=1.8, zorder=13)
    observation = explanation.observation
    if infraction.object_index is not None and step < observation.present.shape[0]:
        _box(
            axes,
            observation.corners[step, infraction.object_index] - origin,
            facecolor=color,
            alpha=0.35,
            edgecolor=color,
            linewidth=1.6,
            zorder=13,
        )
    if infraction.red_light is not None and observation.red_lights is not None:
        light = observation.red_lights.polygons[infraction.red_light]
        _fill(axes, light, origin, fill=False, edgecolor=color, linewidth=1.6, zorder=13)
    # Numbers fan out around their box, so that those of nearby infractions do not cover each other.
    angle = math.radians(40 + 72 * (number - 1))
    axes.annotate(
        str(number),
        ego.mean(axis=0),
        xytext=(20 * math.cos(angle), 20 * math.sin(angle)),
        textcoords="offset points",
        ha="center",
        va="center",
        color="white",
        fontsize="small",
        fontweight="bold",
        zorder=14,
        bbox={"boxstyle": "circle,pad=0.25", "facecolor": color, "edgecolor": "white", "linewidth": 0.8},
        arrowprops={"arrowstyle": "-", "color": color, "linewidth": 1.0, "shrinkA": 0, "shrinkB": 0},
    )
    label = f"{number}  {_infraction_label(infraction)}"
    if INFRACTION_COLUMNS[infraction.kind] in explanation.filtered:
        label += "\n    counts 1: the logged human fails it too"
    return Patch(facecolor="none", edgecolor=color, linewidth=1.8, label=label)


def _infraction_label(infraction: Infraction) -> str:
    """Return an infraction's label: its kind, its time and the object or red-light lane involved, if any."""
    if infraction.red_light is not None:
        what = f" on lane {infraction.object_token}"
    elif infraction.object_token:
        what = f" with {(infraction.object_type or 'object').lower()} {infraction.object_token[:8]}"
    else:
        what = ""
    return f"{infraction.kind} at {infraction.time_s:.1f} s{what}"


def _frame(
    axes: Axes,
    legend_axes: Axes,
    explanation: Explanation,
    origin: FloatArray,
    shape: Layout,
    entries: list[Artist],
    infractions: list[Artist],
) -> float:
    """Set the view, the axis labels and the legends: what is drawn and the infractions, numbered as on the
    map (or that there is none); on a phone the infractions first. Return where the last legend ends (pixels
    from the figure's bottom)."""
    from matplotlib.patches import Patch

    x_low, x_high, y_low, y_high = _extent(explanation, origin, shape)
    axes.set_xlim(x_low, x_high)
    axes.set_ylim(y_low, y_high)
    axes.set_aspect("equal", adjustable="box")
    axes.set_xlabel("x (m from the ego's start)", labelpad=1)
    axes.set_ylabel("y (m)", labelpad=1)
    axes.tick_params(labelsize="small", pad=1.5)
    legend_axes.axis("off")
    off_map = Patch(facecolor=OFF_MAP_COLOR, edgecolor="#9aa2b1", label="not drivable (white)")
    none = Patch(facecolor="none", edgecolor="none", label="none")
    style: dict[str, Any] = {
        "frameon": False,
        "handlelength": 1.6,
        "borderaxespad": 0.0,
        "alignment": "left",
        "title_fontproperties": {"weight": "bold"},
    }
    drawn = {
        "handles": [*entries, off_map],
        "ncols": shape.legend_columns,
        "columnspacing": 0.8,
        "title": "Drawn",
    }
    listed: dict[str, Any] = {
        "handles": infractions or [none],
        "title": "Infractions: the first of each kind",
    }
    # On a phone, what went wrong comes right under the map, before the key to the marks.
    legends = [listed, drawn] if shape.stacked else [drawn, listed]
    renderer = legend_axes.figure.canvas.get_renderer()  # type: ignore[attr-defined]
    top = 1.0
    for options in legends:
        # Each list starts under the one before, wherever its last row ends.
        legend = legend_axes.legend(loc="upper left", bbox_to_anchor=(0.0, top), **options, **style)
        legend_axes.add_artist(legend)
        bottom_px = legend.get_window_extent(renderer).y0
        top = legend_axes.transAxes.inverted().transform((0, bottom_px))[1] - 0.02
    return float(bottom_px)


def _extent(explanation: Explanation, origin: FloatArray, shape: Layout) -> tuple[float, float, float, float]:
    """Return the square view (x low, x high, y low, y high) around what the layout must show, with a margin:
    the submission, its infractions' objects and its synthetic starts, and in the wide layout the human's
    and the reference's paths too."""
    parts = [explanation.agent_states[:, :2]]
    if shape.whole_view:
        parts += [explanation.reference_states[:, :2], explanation.human_future[:, :2]]
    observation = explanation.observation
    for infraction in explanation.infractions:
        step = round(infraction.time_s / SCORING_INTERVAL_S)
        if infraction.object_index is not None and step < observation.present.shape[0]:
            parts.append(observation.corners[step, infraction.object_index])
    if explanation.synthetic_starts is not None:
        parts += [
            explanation.synthetic_starts.start_poses[:, :2],
            explanation.synthetic_starts.endpoint[None],
        ]
    points = np.concatenate(parts) - origin
    points = points[np.isfinite(points).all(axis=1)]
    low, high = points.min(axis=0) - shape.margin_m, points.max(axis=0) + shape.margin_m
    half = max(high - low) / 2  # a square view: equal scale on both axes without distortion
    centre = (low + high) / 2
    return centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half


def _title(explanation: Explanation, width: int) -> str:
    """Return the title: the token and its score, then every subscore in percent (wrapped to `width`), and
    for a stage-one token of a two-stage split, what the starts are."""
    metrics = explanation.metrics
    subscores = "  ".join(  # an undefined value (v2.2's EC of a token drawn alone) is left out
        f"{METRIC_LABELS[column]}\u00a0{100 * value:.1f}"
        for column, value in metrics.items()
        if column != "score" and not math.isnan(value)
    )
    score_label = VERSIONS[explanation.version].score_label
    lines = [
        explanation.token,
        f"{score_label} {explanation.version}: {100 * metrics['score']:.1f} %",
        *textwrap.wrap(subscores, width),
    ]
    notes = []
    if get_version(explanation.version).reactive_traffic is not None:
        notes.append("The vehicles react to your trajectory (IDM).")
    if explanation.synthetic_starts is not None:
        count = len(explanation.synthetic_starts.tokens)
        notes.append(f"Stage one: its {count} synthetic starts, weighted by their distance to your endpoint")
        notes[-1] += (
            f" (none within about 1.9 m: each weighs 1/{count})."
            if explanation.synthetic_starts.weights.uniform_fallback[0]
            else "."
        )
    place = explanation.stage_two_place
    if place is not None:
        notes.append(
            f"Stage two: synthetic start {place.position + 1} of {place.starts} of {place.stage_one}, weighted by "
            f"its distance to that token's endpoint."
        )
    return "\n".join([*lines, *textwrap.wrap(" ".join(notes), width)])
