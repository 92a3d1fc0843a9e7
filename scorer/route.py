"""PDM-Closed's route: loading, correction, starting lane and centerline (docs/engine.md, "PDM-Closed").

The road graph follows the reference run's reading of a map excerpt (tests/fixtures/reference/README.md,
"How the reference run read a scene", items 4-5): a lane's successors are the lane connectors leaving it, in
`lane_connectors` layer order; a roadblock's lanes are those naming it, in `lanes` layer order; a
roadblock's successors are the roadblock connectors leaving it, in layer order. These orders decide
the tie-breaks of the searches below, which mirror the devkit's `route_utils.py`,
`bfs_roadblock.py`, `dijkstra.py` and `abstract_pdm_planner.py` step for step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import shapely

from scorer.drivable_map import DrivableMap, proximal_mask
from scorer.geometry import FloatArray, arctan2_avx512, normalize_angle
from scorer.scene import Lane, MapExcerpt, Roadblock

CANDIDATE_HALF_SIDE = 1.0  # starting-roadblock candidates: square of +-1 m around the rear axle
CANDIDATE_HEADING_ERROR = np.pi / 4
CANDIDATE_DISPLACEMENT_ERROR = 3.0
BACKWARD_SEARCH_DEPTH = 15
FORWARD_SEARCH_DEPTH = 30
ROUTE_TARGETS_AHEAD = 3  # the forward repair search aims at one of the first 3 route blocks
LOOP_OVERLAP_AREA = 1.0  # m^2 of overlap between roadblock connectors that marks a route loop
CENTERLINE_SEARCH_DEPTH = 30  # roadblocks of the route window the centerline search aims at


class RouteError(ValueError):
    """The scene's route cannot be followed (the devkit crashes on these scenes)."""


@dataclass(frozen=True, eq=False)
class RoadGraph:
    """Roadblock and lane graph of a map excerpt, with the devkit's neighbour orders."""

    roadblocks: dict[str, Roadblock]
    roadblock_connectors: dict[str, Roadblock]
    interior: dict[Roadblock, tuple[Lane, ...]]
    block_successors: dict[Roadblock, tuple[Roadblock, ...]]
    block_predecessors: dict[Roadblock, tuple[Roadblock, ...]]
    lane_successors: dict[Lane, tuple[Lane, ...]]
    _paths: dict[Lane, FloatArray] = field(default_factory=dict)
    _lengths: dict[Lane, float] = field(default_factory=dict)

    def block(self, block_id: str) -> Roadblock | None:
        """Return the roadblock with this id, else the roadblock connector, else None (nuPlan's lookup order)."""
        return self.roadblocks.get(block_id) or self.roadblock_connectors.get(block_id)

    def is_connector(self, block: Roadblock) -> bool:
        """Return whether `block` is a roadblock connector."""
        return self.roadblock_connectors.get(block.id) is block

    def discrete_paths(self, lanes: Sequence[Lane]) -> list[FloatArray]:
        """Return each lane's discrete path (n, 3); the ones not yet known are computed in one call."""
        degenerate = [lane.id for lane in lanes if self.lane_length(lane) == 0.0]
        if degenerate:
            # nuPlan asserts on it (`extract_discrete_polyline`): the devkit cannot cache such a scene.
            raise RouteError(
                f"lane {degenerate[0]}: its baseline has zero length, so it has no discrete path"
            )
        self.prefetch(lanes)
        return [self._paths[lane] for lane in lanes]

    def prefetch(self, lanes: Sequence[Lane]) -> None:
        """Compute in one call the discrete paths of lanes read soon (a degenerate one fails only when read)."""
        missing = [
            lane for lane in dict.fromkeys(lanes) if lane not in self._paths and self.lane_length(lane)
        ]
        if missing:
            self._paths.update(zip(missing, baseline_poses([lane.baseline for lane in missing]), strict=True))

    def lane_length(self, lane: Lane) -> float:
        """Return the baseline length as shapely measures it (nuPlan's `baseline_path.length`)."""
        length = self._lengths.get(lane)
        if length is None:
            length = float(shapely.length(shapely.linestrings(lane.baseline)))
            self._lengths[lane] = length
        return length


def baseline_poses(baselines: Sequence[FloatArray]) -> list[FloatArray]:
    """Return the discrete paths (n, 3) of polylines: vertex heading = direction to the next vertex, the last
    repeating the previous (nuPlan's `extract_discrete_polyline`; numpy's AVX-512 arctan2, see geometry)."""
    segments = np.concatenate([np.diff(baseline, axis=0) for baseline in baselines])
    headings = np.split(
        arctan2_avx512(segments[:, 1], segments[:, 0]), np.cumsum([len(b) - 1 for b in baselines])[:-1]
    )
    return [
        np.column_stack([baseline, np.append(heading, heading[-1])])
        for baseline, heading in zip(baselines, headings, strict=True)
    ]


def _group(
    members: Sequence[Lane | Roadblock], key: str, owners: dict[str, Roadblock] | dict[str, Lane]
) -> dict:
    """Return owner -> members whose `key` field (a one-element id list or an id) names it, in member order."""
    grouped: dict = {}
    for member in members:
        value = getattr(member, key)
        owner = owners.get(value if isinstance(value, str) else value[0])
        if owner is not None:
            grouped.setdefault(owner, []).append(member)
    return {owner: tuple(items) for owner, items in grouped.items()}


def build_road_graph(excerpt: MapExcerpt) -> RoadGraph:
    """Return the road graph of a map excerpt; edges come from the connectors, ids absent from it are ignored."""
    lanes = {lane.id: lane for lane in excerpt.lanes}
    roadblocks = {block.id: block for block in excerpt.roadblocks}
    connectors = {block.id: block for block in excerpt.roadblock_connectors}
    interior = _group(excerpt.lanes, "roadblock", roadblocks) | _group(
        excerpt.lane_connectors, "roadblock", connectors
    )
    block_successors = _group(excerpt.roadblock_connectors, "incoming", roadblocks)
    block_predecessors = _group(excerpt.roadblock_connectors, "outgoing", roadblocks)
    lane_successors = _group(excerpt.lane_connectors, "incoming", lanes)
    for connector in excerpt.roadblock_connectors:
        block_successors[connector] = tuple(roadblocks[i] for i in connector.outgoing[:1] if i in roadblocks)
        block_predecessors[connector] = tuple(
            roadblocks[i] for i in connector.incoming[:1] if i in roadblocks
        )
    for lane_connector in excerpt.lane_connectors:
        lane_successors[lane_connector] = tuple(lanes[i] for i in lane_connector.outgoing[:1] if i in lanes)
    return RoadGraph(
        roadblocks=roadblocks,
        roadblock_connectors=connectors,
        interior=interior,
        block_successors=block_successors,
        block_predecessors=block_predecessors,
        lane_successors=lane_successors,
    )


@dataclass(frozen=True, eq=False)
class Route:
    """Route roadblocks (deduplicated, in order) and their lanes / lane connectors (the route-lane dict)."""

    blocks: tuple[Roadblock, ...]
    lanes: tuple[Lane, ...]

    @property
    def block_ids(self) -> tuple[str, ...]:
        """Return the roadblock ids in route order."""
        return tuple(block.id for block in self.blocks)

    @property
    def lane_ids(self) -> tuple[str, ...]:
        """Return the route-lane dict's keys (lanes and lane connectors)."""
        return tuple(dict.fromkeys(lane.id for lane in self.lanes))


def load_route(graph: RoadGraph, block_ids: Sequence[str], token: str) -> Route:
    """Return the route of these roadblock ids (first occurrence kept); a missing id raises.

    See docs/engine.md, "PDM-Closed: route correction".
    """
    blocks: dict[str, Roadblock] = {}
    for block_id in dict.fromkeys(block_ids):
        block = graph.block(block_id)
        if block is None:
            raise RouteError(f"{token}: route roadblock {block_id!r} is not in the map excerpt")
        blocks[block.id] = block
    lanes = {lane.id: lane for block in blocks.values() for lane in graph.interior.get(block, ())}
    return Route(blocks=tuple(blocks.values()), lanes=tuple(lanes.values()))


def _nearest_vertex(poses: FloatArray, x: float, y: float, heading: float) -> tuple[float, float]:
    """Return the distance to the path vertex nearest to (x, y) and the absolute heading error there.

    Heading errors are only compared (thresholds, argmin), so libm's normalisation serves.
    """
    distances = ((poses[:, :2] - np.array([x, y])) ** 2.0).sum(axis=-1) ** 0.5
    nearest = int(np.argmin(distances))
    return float(distances[nearest]), float(np.abs(normalize_angle(poses[nearest, 2] - heading)))


def roadblock_candidates(
    graph: RoadGraph, excerpt: MapExcerpt, route: Route, x: float, y: float, heading: float
) -> tuple[Roadblock, list[Roadblock]]:
    """Return the most promising starting roadblock and the candidate list (`get_current_roadblock_candidates`)."""
    candidates: list[Roadblock] = []
    for layer in (excerpt.roadblocks, excerpt.roadblock_connectors):
        polygons = np.array([block.polygon for block in layer], dtype=object)
        candidates += [layer[i] for i in np.flatnonzero(proximal_mask(polygons, x, y, CANDIDATE_HALF_SIDE))]
    if not candidates:
        # Nothing within the square (e.g. ego in a car park): the nearest object of each layer over the excerpt.
        point = shapely.Point(x, y)
        for layer in (excerpt.roadblocks, excerpt.roadblock_connectors):
            if layer:
                distances = shapely.distance(
                    point, np.array([block.polygon for block in layer], dtype=object)
                )
                candidates.append(layer[int(np.argmin(distances))])
    if not candidates:
        raise RouteError("the map excerpt has no roadblock or roadblock connector")

    route_ids = set(route.block_ids)
    on_route: list[tuple[Roadblock, float]] = []
    off_route: list[tuple[Roadblock, float]] = []
    best_lane_distances = []
    # One call for the candidates' lanes and the route's (the centerline's, in the usual case).
    graph.prefetch(
        [lane for block in candidates for lane in graph.interior.get(block, ())] + list(route.lanes)
    )
    for block in candidates:
        best_distance = np.inf
        lanes = graph.interior.get(block, ())
        for poses in graph.discrete_paths(lanes):
            distance, heading_error = _nearest_vertex(poses, x, y, heading)
            best_distance = min(best_distance, distance)
            if heading_error < CANDIDATE_HEADING_ERROR and distance < CANDIDATE_DISPLACEMENT_ERROR:
                # One entry per qualifying lane, as the devkit appends them.
                (on_route if block.id in route_ids else off_route).append((block, distance))
        best_lane_distances.append(best_distance)
    for qualified in (on_route, off_route):
        if qualified:
            best = int(np.argmin([distance for _, distance in qualified]))
            return qualified[best][0], [block for block, _ in qualified]
    return candidates[int(np.argmin(best_lane_distances))], candidates


def search_blocks(
    graph: RoadGraph, start: Roadblock, targets: Sequence[str], max_depth: int, forward: bool
) -> list[Roadblock] | None:
    """Return the devkit's BFS path from `start` to a target id, or None (`BreadthFirstSearchRoadBlock`).

    The devkit's queue keeps every walk (no visited set) and records the parent of (id, depth) last
    written. Each level is therefore kept as its distinct blocks in order of first appearance (which
    decides the goal found) and of last appearance (which decides the recorded parents), the same
    result without the walks' exponential growth. The path is in driving order.
    """
    neighbours = graph.block_successors if forward else graph.block_predecessors
    target_ids = set(targets)
    parents: dict[tuple[str, int], Roadblock | None] = {(start.id, 1): None}
    first_seen: list[Roadblock] = [start]
    last_seen: list[Roadblock] = [start]
    for depth in range(1, max_depth + 1):
        found = next((block for block in first_seen if block.id in target_ids), None)
        if found is not None:
            path = [found]
            while (parent := parents[(path[-1].id, depth - len(path) + 1)]) is not None:
                path.append(parent)
            return path[::-1] if forward else path
        next_first: dict[str, Roadblock] = {}
        for block in first_seen:
            for successor in neighbours.get(block, ()):
                next_first.setdefault(successor.id, successor)
        next_last: dict[str, Roadblock] = {}
        for block in last_seen:
            for successor in neighbours.get(block, ()):
                parents[(successor.id, depth + 1)] = block
                next_last.pop(successor.id, None)
                next_last[successor.id] = successor
        if not next_first:
            break
        first_seen, last_seen = list(next_first.values()), list(next_last.values())
    return None


def _remove_route_loops(graph: RoadGraph, blocks: list[Roadblock]) -> list[Roadblock]:
    """Cut the route before a roadblock connector overlapping an earlier one by more than 1 m^2 (Fix 3)."""
    seen: list[shapely.Polygon] = []
    for index, block in enumerate(blocks):
        if not graph.is_connector(block):
            continue
        if seen and np.any(
            shapely.area(shapely.intersection(np.array(seen), block.polygon)) > LOOP_OVERLAP_AREA
        ):
            return blocks[:index]
        seen.append(block.polygon)
    return blocks


def correct_route(
    graph: RoadGraph, excerpt: MapExcerpt, route: Route, rear_axle: tuple[float, float, float], token: str
) -> Route:
    """Return the route after PDM-Closed's correction at the ego's rear-axle pose.

    See docs/engine.md, "PDM-Closed: route correction".
    """
    x, y, heading = rear_axle
    start, candidates = roadblock_candidates(graph, excerpt, route, x, y, heading)
    blocks = list(route.blocks)
    block_ids = [block.id for block in blocks]

    # Fix 1: the ego starts off the route.
    if start.id not in block_ids:
        path = search_blocks(
            graph, blocks[0], [block.id for block in candidates], BACKWARD_SEARCH_DEPTH, forward=False
        )
        if path is not None:
            blocks[:0] = path[:-1]
        else:
            path = search_blocks(
                graph, start, block_ids[:ROUTE_TARGETS_AHEAD], FORWARD_SEARCH_DEPTH, forward=True
            )
            if path is not None:
                reached = block_ids.index(path[-1].id)
                blocks = path + blocks[reached + 1 :]

    # Fix 2: link consecutive blocks that are not connected (indices refer to the list before insertion).
    insertions: dict[int, list[Roadblock]] = {}
    for index in range(len(blocks) - 1):
        if any(block.id == blocks[index].id for block in graph.block_predecessors.get(blocks[index + 1], ())):
            continue
        path = search_blocks(graph, blocks[index], [blocks[index + 1].id], FORWARD_SEARCH_DEPTH, forward=True)
        if path is not None and len(path) >= 3:
            insertions[index] = path[1:-1]
    offset = 1
    for index, path in insertions.items():
        blocks[index + offset : index + offset] = path
        offset += len(path)

    # Fix 3: cut route loops.
    blocks = _remove_route_loops(graph, blocks)
    return load_route(graph, [block.id for block in blocks], token)


def starting_lane(
    graph: RoadGraph,
    route: Route,
    drivable_map: DrivableMap,
    drivable_tree: shapely.STRtree,
    rear_axle: tuple[float, float, float],
    center: tuple[float, float],
    footprint: shapely.Polygon,
) -> Lane:
    """Return the route lane the centerline starts from (`_get_starting_lane`).

    See docs/engine.md, "PDM-Closed: starting lane and centerline".
    """
    x, y, heading = rear_axle
    route_lanes = {lane.id: lane for lane in route.lanes}
    touched = drivable_tree.query(shapely.Point(x, y), predicate="intersects")
    on_route = [route_lanes[drivable_map.tokens[i]] for i in touched if drivable_map.tokens[i] in route_lanes]
    if on_route:
        heading_errors = [
            _nearest_vertex(poses, x, y, heading)[1] for poses in graph.discrete_paths(on_route)
        ]
        return on_route[int(np.argmin(heading_errors))]
    # Fallback: the first route lane containing the ego centre, else the one nearest to the ego footprint.
    chosen, closest = None, np.inf
    center_point = shapely.Point(*center)
    for lane in route_lanes.values():
        if lane.polygon.contains(center_point):
            return lane
        distance = lane.polygon.distance(footprint)
        if distance < closest:
            chosen, closest = lane, distance
    if chosen is None:
        raise RouteError("the route has no lanes")
    return chosen


def centerline_lanes(graph: RoadGraph, route: Route, start: Lane) -> list[Lane]:
    """Return the lanes of the centerline: the devkit's Dijkstra towards the route window's last roadblock."""
    block_ids = route.block_ids
    start_index = block_ids.index(start.roadblock) if start.roadblock in block_ids else 0
    target = block_ids[start_index : start_index + CENTERLINE_SEARCH_DEPTH][-1]
    allowed = {lane.id for lane in route.lanes}

    parents: dict[str, Lane | None] = {start.id: None}
    queue: list[Lane] = [start]
    costs: list[float] = [1.0]
    depths: list[int] = [1]
    expanded: list[tuple[Lane, float, int]] = []
    expanded_ids: set[str] = set()
    end = None
    while queue:
        index = int(np.argmin(costs))  # the earliest queue entry on ties
        lane, cost, depth = queue.pop(index), costs.pop(index), depths.pop(index)
        if lane.roadblock == target:
            end = lane
            break
        expanded.append((lane, cost, depth))
        expanded_ids.add(lane.id)
        for successor in graph.lane_successors.get(lane, ()):
            if successor.id not in allowed:
                continue
            alternative = cost + graph.lane_length(successor)
            queued = [i for i, item in enumerate(queue) if item.id == successor.id]
            if successor.id not in expanded_ids and not queued:
                parents[successor.id] = lane
                queue.append(successor)
                costs.append(alternative)
                depths.append(depth + 1)
            elif queued and alternative < costs[queued[0]]:
                parents[successor.id] = lane
                costs[queued[0]] = alternative
                depths[queued[0]] = depth + 1
    if end is None:
        # Not reached: the cheapest of the deepest expanded lanes.
        deepest = max(depth for _, _, depth in expanded)
        at_depth = [(cost, lane) for lane, cost, depth in expanded if depth == deepest]
        end = at_depth[int(np.argmin([cost for cost, _ in at_depth]))][1]
    path = [end]
    while (parent := parents[path[-1].id]) is not None:
        path.append(parent)
    return path[::-1]


def discrete_centerline(graph: RoadGraph, lanes: Sequence[Lane]) -> FloatArray:
    """Return the centerline (n, 3): the lanes' discrete paths concatenated, shared vertices kept twice."""
    return np.concatenate(graph.discrete_paths(lanes), axis=0)
