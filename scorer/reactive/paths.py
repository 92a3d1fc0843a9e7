"""An IDM vehicle's path: the baseline of its starting lane or lane connector, as nuPlan's IDM agent holds it
(docs/engine.md, "Reactive traffic: building the agents").

nuPlan turns the baseline into `StateSE2` vertices (`extract_discrete_polyline`: the heading of a vertex is
numpy's `arctan2` towards the next one, the last vertex repeats the one before), measures the cumulative
progress as numpy's `linalg.norm` of the coordinate differences (sqrt(dx * dx + dy * dy), then `cumsum`), and
`create_path_from_se2` keeps vertex i only where progress[i + 1] - progress[i] is not `isclose` to 0: the zip
over the n - 1 differences drops the **last vertex** always, so a path ends at the second-to-last baseline
vertex. `InterpolatedPath` interpolates x, y and the `np.unwrap`ped headings with scipy's linear `interp1d`
and wraps the heading with `principal_value`. The trims (`trim_path_up_to_progress`, `trim_path`) keep
nuPlan's odd ends: with nothing left ahead, the path's last two vertices.

A path is read one progress at a time (the IDM's loop is sequential, `scorer.reactive.traffic`), so the
interpolation is scalar, in the order of scipy's `_call_linear`. For the lazy occupancy
(`scorer.reactive.occupancy`) a path also gives the envelope of what lies ahead of a progress without building
it, from the envelopes of its vertices' suffixes, computed once per path.
"""

from __future__ import annotations

import bisect
import itertools
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from scorer.geometry import FloatArray, arctan2_avx512, principal_value_of

RECENT_STATES = 16  # how many states at a progress a path keeps (`LanePath.state_at`)


class PathError(ValueError):
    """A baseline nuPlan's IDM cannot make a path of (the official token fails)."""


@dataclass(frozen=True, eq=False)
class LanePath:
    """The vertices of an IDM path: progress (n,) from 0, x, y (n, 2) and unwrapped headings (n,)."""

    progress: tuple[float, ...]
    points: FloatArray  # (n, 2)
    unwrapped_heading: tuple[float, ...]

    @classmethod
    def of_baseline(cls, baseline: FloatArray) -> LanePath:
        """Return the path nuPlan's IDM agent makes of a baseline (n, 2); raise PathError where it asserts."""
        differences = np.diff(baseline, axis=0)
        heading = arctan2_avx512(differences[:, 1], differences[:, 0])
        heading = np.append(heading, heading[-1])
        squares = differences * differences
        progress = np.cumsum(np.append(0.0, np.sqrt(squares[:, 0] + squares[:, 1])))
        kept = np.flatnonzero(~np.isclose(np.diff(progress), 0.0))
        if len(kept) < 2:
            raise PathError(
                f"the IDM cannot make a path of a {len(baseline)}-vertex baseline (it keeps {len(kept)} vertex)"
            )
        return cls(
            progress=tuple(progress[kept].tolist()),
            points=np.ascontiguousarray(baseline[kept]),
            unwrapped_heading=tuple(np.unwrap(heading[kept]).tolist()),
        )

    @property
    def start(self) -> float:
        """Return the progress of the path's first vertex (0)."""
        return self.progress[0]

    @property
    def end(self) -> float:
        """Return the progress of the path's last vertex: where an IDM vehicle stops."""
        return self.progress[-1]

    def clamp(self, progress: float) -> float:
        """Return `progress` clamped to the path (nuPlan's `_clamp_progress`)."""
        return max(self.progress[0], min(progress, self.progress[-1]))

    def state_at(self, progress: float) -> tuple[float, float, float]:
        """Return x, y and heading (wrapped to [-pi, pi)) at `progress` on the path, as `get_state_at_progress`.

        Memoised by progress, a few at a time: a step reads the state at a vehicle's progress for its pose,
        its path ahead and the envelope of it, and the simulations of one scene begin alike."""
        states = self._recent_states
        state = states.get(progress)
        if state is None:
            if len(states) >= RECENT_STATES:
                states.clear()
            state = states[progress] = self._interpolated_state(progress)
        return state

    @cached_property
    def _recent_states(self) -> dict[float, tuple[float, float, float]]:
        return {}

    def _interpolated_state(self, progress: float) -> tuple[float, float, float]:
        upper = min(max(bisect.bisect_left(self.progress, progress), 1), len(self.progress) - 1)
        lower = upper - 1
        low, high = self.progress[lower], self.progress[upper]
        offset = progress - low
        span = high - low
        (x_low, y_low), (x_high, y_high) = self.vertices[lower], self.vertices[upper]
        heading_low, heading_high = self.unwrapped_heading[lower], self.unwrapped_heading[upper]
        x = (x_high - x_low) / span * offset + x_low
        y = (y_high - y_low) / span * offset + y_low
        heading = (heading_high - heading_low) / span * offset + heading_low
        return x, y, principal_value_of(heading)

    def to_go(self, progress: float) -> FloatArray:
        """Return the points (m, 2) of the path from `progress` (clamped) on (`trim_path_up_to_progress`)."""
        start, first = self.to_go_parts(progress)
        if start is None:
            return self.points[first:]
        # Filled in place: `np.concatenate` of the point's list costs more than the copy (the same floats).
        points = np.empty((len(self.progress) - first + 1, 2))
        points[0] = start
        points[1:] = self.points[first:]
        return points

    def to_go_parts(self, progress: float) -> tuple[tuple[float, float] | None, int]:
        """Return what `to_go(progress)` is made of: the point it starts at (None: at a vertex) and the
        first of the path's vertices that follow it."""
        ahead = bisect.bisect_right(self.progress, progress)
        if ahead == len(self.progress):
            return None, len(self.progress) - 2
        x, y, _ = self.state_at(progress)
        return (x, y), ahead

    def to_go_start(self, progress: float) -> tuple[float, float]:
        """Return the first point of `to_go(progress)`."""
        start, first = self.to_go_parts(progress)
        return start if start is not None else self.vertices[first]

    @cached_property
    def vertices(self) -> list[tuple[float, float]]:
        """Return the vertices' x, y in Python floats."""
        return [(x, y) for x, y in self.points.tolist()]

    @cached_property
    def segments(self) -> list[tuple[float, float, float, float]]:
        """Return the segments between consecutive vertices: x0, y0, x1, y1 in Python floats."""
        return [(x0, y0, x1, y1) for (x0, y0), (x1, y1) in itertools.pairwise(self.vertices)]

    @cached_property
    def identity(self) -> bytes:
        """Return what names the path process-wide: its vertices and their progress (bytes, whose hash
        Python keeps)."""
        return self.points.tobytes() + np.array(self.progress).tobytes()

    @cached_property
    def _envelopes_ahead(self) -> list[tuple[float, float, float, float]]:
        """Per vertex the envelope (min x, min y, max x, max y) of it and every vertex after it."""
        backwards = self.points[::-1]
        lows = np.minimum.accumulate(backwards, axis=0)[::-1]
        highs = np.maximum.accumulate(backwards, axis=0)[::-1]
        return [tuple(row) for row in np.concatenate([lows, highs], axis=1).tolist()]

    def to_go_envelope(self, progress: float, margin: float) -> tuple[float, float, float, float]:
        """Return the envelope of `to_go(progress)`, widened by `margin` on every side."""
        ahead = bisect.bisect_right(self.progress, progress)
        if ahead == len(self.progress):
            low_x, low_y, high_x, high_y = self._envelopes_ahead[-2]
        else:
            x, y, _ = self.state_at(progress)
            low_x, low_y, high_x, high_y = self._envelopes_ahead[ahead]
            low_x, low_y, high_x, high_y = min(x, low_x), min(y, low_y), max(x, high_x), max(y, high_y)
        return low_x - margin, low_y - margin, high_x + margin, high_y + margin

    def between(self, start: float, end: float) -> FloatArray:
        """Return the points (m, 2) of the path from `start` to `end` (both clamped; nuPlan's `trim_path`)."""
        ends, first, last = self.between_parts(start, end)
        if ends is None:
            return self.points[first : last + 1]
        start_point, end_point = ends
        points = np.empty((max(last + 1 - first, 0) + 2, 2))  # filled in place, as in `to_go`
        points[0] = start_point
        points[1:-1] = self.points[first : last + 1]
        points[-1] = end_point
        return points

    def between_parts(
        self, start: float, end: float
    ) -> tuple[tuple[tuple[float, float], tuple[float, float]] | None, int, int]:
        """Return what `between(start, end)` is made of: the points it starts and ends at (None: it is two of
        the path's vertices) and the first and last of the path's vertices between them (last < first:
        none)."""
        first = bisect.bisect_right(self.progress, start)
        if first == len(self.progress):
            return None, len(self.progress) - 2, len(self.progress) - 1
        last = bisect.bisect_left(self.progress, end) - 1
        if last < 0:
            return None, 0, 1
        x_start, y_start, _ = self.state_at(start)
        x_end, y_end, _ = self.state_at(end)
        return ((x_start, y_start), (x_end, y_end)), first, last
