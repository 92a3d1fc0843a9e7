"""Red lights as NAVSIM v2's observations hold them: lane polygons that the ego must not touch
(docs/engine.md, "v2.2: traffic-light compliance").

v2's metric cache puts into every 10 Hz occupancy map the polygon of each on-route lane or lane connector
whose light is RED in the 2 Hz frame of that step, sample-and-held (`_interpolate_traffic_light_status`:
frame `k // 5` for step k), under the token `red_light_<id>`. Its on-route set comes from the current
frame's route as logged, not corrected (`_load_route_dicts`): each roadblock (else roadblock connector) and
all its lanes or lane connectors. Entries are read in file order, and a RED id listed twice adds two
polygons. PDM-Closed's own forecast holds the current frame's lights on its corrected route at every step
(`scorer.planner_observation`).

Lights are kept apart from the tracked boxes (`scorer.observation`): NC and TTC skip them by name, only
traffic-light compliance reads them, and they are lane polygons, not boxes.
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import shapely

from scorer.geometry import BoolArray, FloatArray
from scorer.scene import Lane, Scene

RED_LIGHT_TOKEN = "red_light"  # the devkit recognises red lights by this token prefix
STEPS_PER_FRAME = 5  # 10 Hz steps per 2 Hz frame


class RedLights(NamedTuple):
    """Red-light polygons and the 10 Hz steps at which each is in the occupancy map."""

    lane_ids: tuple[str, ...]  # (n,) the lane or lane connector of each polygon
    polygons: npt.NDArray[np.object_]  # (n,)
    present: BoolArray  # (T, n)

    @classmethod
    def none(cls, num_steps: int) -> "RedLights":
        """Return an observation without red lights over `num_steps` steps."""
        return cls(
            lane_ids=(), polygons=np.empty(0, dtype=object), present=np.zeros((num_steps, 0), dtype=bool)
        )

    @classmethod
    def constant(cls, lanes: Sequence[Lane], num_steps: int) -> "RedLights":
        """Return the red lights of `lanes` present at every step."""
        polygons = np.empty(len(lanes), dtype=object)
        polygons[:] = [lane.polygon for lane in lanes]
        present = np.ones((num_steps, len(lanes)), dtype=bool)
        return cls(lane_ids=tuple(lane.id for lane in lanes), polygons=polygons, present=present)

    @property
    def tokens(self) -> tuple[str, ...]:
        """Return each polygon's token in the occupancy map."""
        return tuple(f"{RED_LIGHT_TOKEN}_{lane_id}" for lane_id in self.lane_ids)

    @property
    def bounds(self) -> FloatArray:
        """Return the polygons' bounding boxes (n, 4)."""
        return shapely.bounds(self.polygons).reshape(-1, 4)


def red_lanes(lights: Sequence[tuple[str, bool]], route_lanes: Mapping[str, Lane]) -> list[Lane]:
    """Return the on-route lanes of a frame's RED entries, in file order (`_get_traffic_light_geometries`)."""
    return [route_lanes[lane_id] for lane_id, is_red in lights if is_red and lane_id in route_lanes]


def observe_red_lights(scene: Scene, future_frames: int) -> RedLights:
    """Return the red lights of the current frame and `future_frames` frames after it, at 10 Hz steps."""
    from scorer.route import build_road_graph, load_route  # caches only: warm scoring starts without it

    graph = build_road_graph(scene.map)
    route = load_route(graph, scene.current_frame.route_roadblocks, scene.token)
    route_lanes = {lane.id: lane for lane in route.lanes}
    frames = scene.frames[scene.current_index : scene.current_index + future_frames + 1]
    per_frame = [red_lanes(frame.traffic_lights, route_lanes) for frame in frames]
    lanes = [lane for frame_lanes in per_frame for lane in frame_lanes]
    frame_of = np.repeat(np.arange(len(frames)), [len(frame_lanes) for frame_lanes in per_frame])
    num_steps = future_frames * STEPS_PER_FRAME + 1
    step_frame = np.minimum(np.arange(num_steps) // STEPS_PER_FRAME, future_frames)
    polygons = np.empty(len(lanes), dtype=object)
    polygons[:] = [lane.polygon for lane in lanes]
    return RedLights(
        lane_ids=tuple(lane.id for lane in lanes),
        polygons=polygons,
        present=step_frame[:, None] == frame_of[None, :],
    )
