"""The navigation goal (driving command) of a frame, computed from its route as OpenScene's generator does.

OpenScene (`helpers/driving_command.py`) corrects the route like PDM-Closed, starts from the route
lane that contains the rear axle (else the nearest one), follows the Dijkstra centerline, and looks
at the centerline pose 20 m beyond the rear axle's projection: seen from the centerline pose at the
projection, a lateral offset of at least +2 m means left, at most -2 m right, anything else straight.
No route, or a route the correction cannot attach the ego to, gives unknown.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import shapely

from scorer.geometry import normalize_angle
from scorer.openscene.frames import EgoPose
from scorer.pdm_closed import PdmPath, interpolate_paths
from scorer.route import (
    BACKWARD_SEARCH_DEPTH,
    RoadGraph,
    Route,
    RouteError,
    build_road_graph,
    centerline_lanes,
    correct_route,
    discrete_centerline,
    load_route,
    roadblock_candidates,
    search_blocks,
)
from scorer.scene import Lane, MapExcerpt

LEFT, STRAIGHT, RIGHT, UNKNOWN = [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]
LOOKAHEAD_M = 20.0
LATERAL_THRESHOLD_M = 2.0


def navigation_command(excerpt: MapExcerpt, pose: EgoPose, route_ids: Sequence[str]) -> list[int]:
    """Return the one-hot [left, straight, right, unknown] command of a rear-axle pose and its route."""
    graph = build_road_graph(excerpt)
    try:
        route = load_route(graph, route_ids, "navigation goal")
        if not route.blocks or _off_route_without_way_back(graph, excerpt, route, pose):
            return list(UNKNOWN)
        route = correct_route(graph, excerpt, route, (pose.x, pose.y, pose.heading), "navigation goal")
        lanes = centerline_lanes(graph, route, _current_lane(route, pose))
    except RouteError:
        return list(UNKNOWN)  # the generator crashes on such routes; unknown is the honest command
    path = PdmPath.from_poses(discrete_centerline(graph, lanes))
    progress = path.linestring.project(shapely.Point(pose.x, pose.y))
    last_vertex = np.array([len(path.progress) - 1])
    distances = np.array([[progress, progress + LOOKAHEAD_M]])
    current, target = interpolate_paths(
        path.states[None], path.progress[None], last_vertex, distances, normalize_angle
    )[0]
    # Lateral coordinate of the target in the frame of the current centerline pose.
    lateral = -(target[0] - current[0]) * np.sin(current[2]) + (target[1] - current[1]) * np.cos(current[2])
    if lateral >= LATERAL_THRESHOLD_M:
        return list(LEFT)
    if lateral <= -LATERAL_THRESHOLD_M:
        return list(RIGHT)
    return list(STRAIGHT)


def _off_route_without_way_back(graph: RoadGraph, excerpt: MapExcerpt, route: Route, pose: EgoPose) -> bool:
    """Return whether the ego starts off the route and no route block leads back to it.

    OpenScene's correction gives up there, where PDM-Closed's searches forward from the ego instead.
    """
    start, candidates = roadblock_candidates(graph, excerpt, route, pose.x, pose.y, pose.heading)
    if start.id in route.block_ids:
        return False
    path = search_blocks(
        graph, route.blocks[0], [block.id for block in candidates], BACKWARD_SEARCH_DEPTH, forward=False
    )
    return path is None


def _current_lane(route: Route, pose: EgoPose) -> Lane:
    """Return the route lane containing the rear axle, the first in route order, else the nearest one."""
    rear_axle = shapely.Point(pose.x, pose.y)
    polygons = np.array([lane.polygon for lane in route.lanes], dtype=object)
    if not len(polygons):
        raise RouteError("the route has no lanes")
    containing = np.flatnonzero(shapely.contains(polygons, rear_axle))
    if len(containing):
        return route.lanes[containing[0]]
    return route.lanes[int(np.argmin(shapely.distance(polygons, rear_axle)))]
