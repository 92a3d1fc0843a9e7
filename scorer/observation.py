"""The evaluation observation: the recorded future of every tracked object at 10 Hz
(docs/engine.md, "Observation and forecasts: the recorded future").

NAVSIM's metric caching (`_interpolate_gt_observation`) takes the boxes of the current frame and the 10
frames after it (2 Hz, 0.0 ... 5.0 s), interpolates each track linearly to 51 occupancy maps at 0.1 s
and keeps, per track, the object of its first appearance ("unique object") for collision classes.
Scene files hold boxes in the global frame already, so they are used as given (no ego-frame step).

Quirks kept on purpose (docs/engine.md, "Observation and forecasts: the recorded future"): a track
seen in exactly one frame stands still at that box in all 51 maps, also before and after the frame it
was seen in; a track seen more often exists from its first to its last sighting, gaps bridged
linearly; length, width and type come from the first sighting. Interpolated headings are wrapped with
the AVX-512 arctan2 of the machine that made the official results (`geometry.normalize_angle`).
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple, cast

import numpy as np
import numpy.typing as npt
import shapely

from scorer.geometry import BoolArray, FloatArray, IntArray, box_corners, normalize_angle
from scorer.red_lights import RED_LIGHT_TOKEN, STEPS_PER_FRAME, RedLights
from scorer.scene import AGENT_CATEGORIES, FUTURE_FRAMES, Scene

OBSERVATION_STEPS = FUTURE_FRAMES * STEPS_PER_FRAME + 1  # v1: occupancy maps at k * 0.1 s, k = 0..50
STEP_S = 0.1
FRAME_INTERVAL_S = 0.5  # the devkit samples the recorded boxes at 2 Hz
_AGENT_CATEGORIES = frozenset(AGENT_CATEGORIES)


@dataclass(frozen=True, eq=False)
class Observation:
    """Occupancy maps (T time indices x n objects) and each object's first appearance.

    Objects are boxes, held as corners: shapely polygons cost more to build than most scoring steps,
    and the scorer needs them only for the few pairs its exact box tests cannot decide. Only the present
    boxes are held, as a metric cache stores them: a batch puts them in place in its own dense maps
    (`ObservationBatch`), and an observation's dense maps (`corners`) are made where read.
    """

    tokens: tuple[str, ...]  # n track tokens, first-appearance order
    object_types: tuple[str, ...]  # nuPlan type at first appearance, e.g. "VEHICLE", "TRAFFIC_CONE"
    is_agent: BoolArray  # (n,) vehicle, pedestrian or bicycle at first appearance (nuPlan `Agent`)
    first_speed: FloatArray  # (n,) |velocity| at first appearance (0 for static objects)
    present: BoolArray  # (T, n) the object is in occupancy map k
    # (k, 4, 2) the corners FL, RL, RR, FR (the devkit's ring order) of the k present boxes, in the C order of
    # `present`: step by step, each step's in column order
    boxes: FloatArray
    red_lights: RedLights | None = None  # v2's red-light polygons (None: the version reads none)

    @cached_property
    def corners(self) -> FloatArray:
        """Return the box corners (T, n, 4, 2), NaN where absent."""
        return joined_corners([self.present], [self.boxes])

    @cached_property
    def polygons(self) -> npt.NDArray[np.object_]:
        """Return the box polygons (T, n), None where absent."""
        polygons = np.full(self.present.shape, None, dtype=object)
        polygons[self.present] = shapely.polygons(self.boxes)
        return polygons

    @cached_property
    def is_red_light(self) -> BoolArray:
        """Return which tokens are red-light pseudo-obstacles (the devkit tests for this substring)."""
        return np.array([RED_LIGHT_TOKEN in token for token in self.tokens], dtype=bool)


_BOX_BYTES = np.dtype((np.void, 8 * np.dtype(np.float64).itemsize))  # a box's 4 corners as one item
_ABSENT = np.full(8, np.nan).view(_BOX_BYTES)[0]


def _box_items(corners: FloatArray) -> np.ndarray:
    """Return C-contiguous corners (..., 4, 2) viewed as one item per box (...)."""
    return corners.reshape(*corners.shape[:-2], 8).view(_BOX_BYTES)[..., 0]


def joined_corners(presents: Sequence[BoolArray], boxes: Sequence[FloatArray]) -> FloatArray:
    """Return the corners (T, N, 4, 2) of observations side by side, NaN where absent, from each one's presence
    (T, n) and its present boxes (k, 4, 2) in its C order.

    Each observation's boxes are put in place in the joined array, without a dense array of their own to copy
    in; each box's 8 values move as one item: numpy copies an indexed item several times faster than an
    indexed row of 8 floats.
    """
    present = np.concatenate(presents, axis=1)
    corners = np.empty((*present.shape, 4, 2))
    items = _box_items(corners)
    start = 0
    for observation_present, observation_boxes in zip(presents, boxes, strict=True):
        end = start + observation_present.shape[1]
        items[:, start:end][observation_present] = _box_items(np.ascontiguousarray(observation_boxes))
        start = end
    items[~present] = _ABSENT
    return corners


class ObservationBatch(NamedTuple):
    """The observations of several scene tokens side by side: object j of token b is column start[b] + j."""

    corners: FloatArray  # (T, N, 4, 2) box corners, NaN where absent
    extent: FloatArray  # (N, 4) xmin, ymin, xmax, ymax over all steps
    is_agent: BoolArray  # (N,)
    first_speed: FloatArray  # (N,)
    is_red_light: BoolArray  # (N,)
    start: IntArray  # (B,) first column of each token
    counts: IntArray  # (B,) objects of each token

    @classmethod
    def of(cls, observations: Sequence[Observation]) -> "ObservationBatch":
        """Return the batch of `observations`, in order."""
        count = np.array([len(observation.tokens) for observation in observations], dtype=np.intp)

        def joined(name: str) -> np.ndarray:
            return np.concatenate([getattr(observation, name) for observation in observations])

        corners = joined_corners(
            [observation.present for observation in observations],
            [observation.boxes for observation in observations],
        )
        return cls(
            corners=corners,
            extent=_extents(corners),
            is_agent=joined("is_agent").astype(bool),
            first_speed=joined("first_speed").astype(np.float64),
            is_red_light=joined("is_red_light").astype(bool),
            start=np.cumsum(count) - count,
            counts=count,
        )


def _extents(corners: FloatArray) -> FloatArray:
    """Return each object's bounding box (N, 4) over all its corners (T, N, 4, 2), absent steps (NaN) left out.

    Over the steps first, where the corners lie contiguous: one pass over the batch in two calls, where
    reducing each box's 4 corners first strides through it; then over the 4 corners, a column pair at a time
    (numpy reduces a short axis slowly). Minima round nothing, and the extents only prune candidate pairs
    (`scorer.metrics.pairs`).
    """
    per_object = corners.reshape(*corners.shape[:2], 8)  # x, y of the 4 corners
    lower = np.fmin.reduce(per_object, axis=0)
    upper = np.fmax.reduce(per_object, axis=0)

    def over_corners(pick: np.ufunc, values: FloatArray, coordinate: int) -> FloatArray:
        columns = [values[:, 2 * corner + coordinate] for corner in range(4)]
        return cast(FloatArray, pick(pick(columns[0], columns[1]), pick(columns[2], columns[3])))

    return np.stack(
        [over_corners(np.fmin, lower, 0), over_corners(np.fmin, lower, 1)]
        + [over_corners(np.fmax, upper, 0), over_corners(np.fmax, upper, 1)],
        axis=-1,
    )


def _track_indices(tracks: Sequence[str]) -> tuple[IntArray, IntArray]:
    """Return each sighting's track index (tracks in first-appearance order) and each track's first row.

    One pass over the names in a dict: a scene has a few hundred sightings, which converting and sorting as
    numpy strings (np.unique) took several times as long to index."""
    index_of: dict[str, int] = {}
    first_rows: list[int] = []
    track_index = []
    for row, track in enumerate(tracks):
        index = index_of.setdefault(track, len(first_rows))
        if index == len(first_rows):
            first_rows.append(row)
        track_index.append(index)
    return np.array(track_index, dtype=np.intp), np.array(first_rows, dtype=np.intp)


def observe_scene(scene: Scene, future_frames: int = FUTURE_FRAMES) -> Observation:
    """Return the 10 Hz evaluation observation of the scene's current frame and `future_frames` frames after
    it (v1: 10, 51 steps; v2: 8, 41 steps).

    See docs/engine.md, "Observation and forecasts: the recorded future".
    """
    frames = scene.frames[scene.current_index : scene.current_index + future_frames + 1]
    frame_of = np.concatenate([np.full(len(frame.tracks), index) for index, frame in enumerate(frames)])
    tracks = [track for frame in frames for track in frame.tracks]
    categories = [category for frame in frames for category in frame.categories]
    boxes = np.concatenate([frame.boxes for frame in frames]).reshape(-1, 7)
    velocities = np.concatenate([frame.velocities for frame in frames]).reshape(-1, 2)
    # The devkit records a velocity only for agent types; static objects keep zeros.
    sighted_agent = np.array([category in _AGENT_CATEGORIES for category in categories], dtype=bool)
    velocities = np.where(sighted_agent[:, None], velocities, 0.0)

    track_index, first_rows = _track_indices(tracks)
    samples = _track_samples(track_index, frame_of, boxes, velocities, len(first_rows), len(frames))

    is_agent = sighted_agent[first_rows]
    present, states = _interpolate_tracks(*samples, future_frames * STEPS_PER_FRAME + 1)
    # A track seen once is the unchanged first sighting at every step (no interpolation, no wrap).
    single = samples[2] == 1
    present[:, single] = True
    states[:, single] = boxes[first_rows][single][:, [0, 1, 6]]

    half_length = boxes[first_rows, 3] / 2.0
    half_width = boxes[first_rows, 4] / 2.0
    corners = box_corners(states[..., 0], states[..., 1], states[..., 2], half_length, half_width)
    return Observation(
        tokens=tuple(tracks[row] for row in first_rows.tolist()),
        object_types=tuple(categories[row].upper() for row in first_rows.tolist()),
        is_agent=is_agent,
        first_speed=np.where(is_agent, np.hypot(*velocities[first_rows].T), 0.0),
        present=present,
        boxes=corners[present],
    )


def _track_samples(
    track_index: IntArray, frame_of: IntArray, boxes: FloatArray, velocities: FloatArray, n: int, frames: int
) -> tuple[FloatArray, FloatArray, IntArray]:
    """Return per track its sighting times (n, frames), states (n, frames, 5) and sighting count (n,).

    States are x, y, heading (unwrapped over the track's own sightings), vx, vy; slots past a track's
    last sighting repeat it (times +inf), which neither the unwrap nor the interpolation reads.
    """
    counts = np.bincount(track_index, minlength=n)
    # Sightings come frame by frame, so each track's rows are already in time order.
    slot = np.zeros(len(track_index), dtype=np.intp)
    order = np.argsort(track_index, kind="stable")
    starts = np.cumsum(counts) - counts
    slot[order] = np.arange(len(track_index)) - np.repeat(starts, counts)
    times = np.full((n, frames), np.inf)
    times[track_index, slot] = frame_of * FRAME_INTERVAL_S
    states = np.zeros((n, frames, 5))
    states[track_index, slot] = np.column_stack([boxes[:, [0, 1, 6]], velocities])
    last = np.maximum(counts - 1, 0)
    padding = np.arange(frames)[None, :] > last[:, None]
    states[padding] = np.repeat(states[np.arange(n), last], frames - 1 - last, axis=0)
    states[..., 2] = np.unwrap(states[..., 2], axis=1)
    return times, states, counts


def _interpolate_tracks(
    times: FloatArray, states: FloatArray, counts: IntArray, num_steps: int
) -> tuple[BoolArray, FloatArray]:
    """Return presence (T, n) and x, y, heading (T, n, 3) at k * 0.1 s, as scipy's `interp1d` per track; the
    heading wrapped where a track seen more than once is present (elsewhere it is not read)."""
    query = np.arange(num_steps, dtype=np.float64) * STEP_S
    first = times[:, 0]
    last = np.take_along_axis(times, np.maximum(counts - 1, 0)[:, None], axis=1)[:, 0]
    present = (first[None, :] <= query[:, None]) & (query[:, None] <= last[None, :])
    # interp1d: searchsorted (side left) clipped to [1, count - 1] picks the interval.
    upper = (times[None, :, :] < query[:, None, None]).sum(axis=-1)
    upper = np.clip(upper, 1, np.maximum(counts - 1, 1)[None, :])
    lower = upper - 1
    track = np.arange(len(counts))[None, :]
    low_time, high_time = times[track, lower], times[track, upper]
    low, high = states[track, lower], states[track, upper]
    with np.errstate(invalid="ignore"):
        slope = (high - low) / (high_time - low_time)[..., None]
        interpolated = slope * (query[:, None] - low_time)[..., None] + low
    result = interpolated[..., :3]
    # Only the headings of boxes kept are wrapped (the arctan2 replay costs per element): the present steps of
    # tracks seen more than once; a track seen once takes its sighting unchanged (`observe_scene`).
    kept = present & (counts > 1)[None, :]
    result[..., 2][kept] = normalize_angle(result[..., 2][kept])
    return present, result


def drop_tracks_on_ego(
    observation: Observation, ego_footprint: shapely.Polygon
) -> tuple[Observation, tuple[str, ...]]:
    """Return the observation without the tracks whose box touches the ego's at step 0, and their tokens.

    v2's non-reactive traffic (`LogReplayTrafficAgents.simulate_environment`) tests every object of the
    first occupancy map, static objects too, with `intersects` against the initial ego footprint, and
    drops those tracks from every step before any metric. Red lights are not tracks.
    """
    touching = np.zeros(len(observation.tokens), dtype=bool)
    first = np.flatnonzero(observation.present[0])
    # Only step 0's boxes, the first: `polygons` would build all the steps' (the scorer's exact box tests need
    # none).
    touching[first] = shapely.intersects(shapely.polygons(observation.boxes[: len(first)]), ego_footprint)
    kept = np.flatnonzero(~touching)
    dropped = tuple(observation.tokens[index] for index in np.flatnonzero(touching))
    return (
        Observation(
            tokens=tuple(observation.tokens[index] for index in kept),
            object_types=tuple(observation.object_types[index] for index in kept),
            is_agent=observation.is_agent[kept],
            first_speed=observation.first_speed[kept],
            present=observation.present[:, kept],
            boxes=observation.boxes[~touching[np.nonzero(observation.present)[1]]],
            red_lights=observation.red_lights,
        ),
        dropped,
    )
