"""Route loading, correction, searches and discrete paths on hand-built maps (spec 9.1, 9.2)."""

from __future__ import annotations

import itertools
import math
from collections import deque

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from scorer.route import (
    Route,
    RouteError,
    baseline_poses,
    build_road_graph,
    centerline_lanes,
    correct_route,
    load_route,
    search_blocks,
)
from scorer.scene import Lane, MapExcerpt, Roadblock

SQUARE = shapely.box(0.0, 0.0, 1.0, 1.0)


def _block(block_id: str, polygon: shapely.Polygon = SQUARE) -> Roadblock:
    return Roadblock(id=block_id, polygon=polygon, incoming=(), outgoing=(), lanes=())


def _connector(block_id: str, source: str, target: str, polygon: shapely.Polygon = SQUARE) -> Roadblock:
    return Roadblock(id=block_id, polygon=polygon, incoming=(source,), outgoing=(target,), lanes=())


def _lane(lane_id: str, block: str, baseline: list[list[float]], source: str = "", target: str = "") -> Lane:
    points = np.array(baseline, dtype=np.float64)
    return Lane(
        id=lane_id,
        polygon=shapely.buffer(shapely.linestrings(points), 1.5, cap_style="flat"),
        roadblock=block,
        baseline=points,
        speed_limit_mps=None,
        incoming=(source,) if source else (),
        outgoing=(target,) if target else (),
    )


def _straight_road() -> MapExcerpt:
    """Roadblocks 1 -> 2 -> 3 along +x (each 10 m, one lane), joined by connectors 12, 23."""
    blocks = [_block(str(i), shapely.box(10 * (i - 1), -2, 10 * i, 2)) for i in (1, 2, 3)]
    connectors = [
        _connector("12", "1", "2", shapely.box(9, -2, 11, 2)),
        _connector("23", "2", "3", shapely.box(19, -2, 21, 2)),
    ]
    lanes = [_lane(f"{i}0", str(i), [[10 * (i - 1), 0], [10 * i - 1, 0]]) for i in (1, 2, 3)]
    lane_connectors = [
        _lane("120", "12", [[9, 0], [11, 0]], "10", "20"),
        _lane("230", "23", [[19, 0], [21, 0]], "20", "30"),
    ]
    return MapExcerpt(
        lanes=tuple(lanes),
        lane_connectors=tuple(lane_connectors),
        roadblocks=tuple(blocks),
        roadblock_connectors=tuple(connectors),
    )


def test_baseline_headings_point_to_the_next_vertex_and_repeat_at_the_end() -> None:
    poses = baseline_poses([np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 1.0], [1.0, 3.0]])])[0]
    assert poses[:, :2].tolist() == [[0.0, 0.0], [1.0, 1.0], [1.0, 1.0], [1.0, 3.0]]
    # 45 degrees, a zero-length segment gives 0, north, and the last vertex repeats the previous heading.
    assert poses[:, 2].tolist() == [math.pi / 4, 0.0, math.pi / 2, math.pi / 2]


def test_graph_edges_come_from_the_connectors_in_layer_order() -> None:
    excerpt = _straight_road()
    graph = build_road_graph(excerpt)
    block = {b.id: b for b in excerpt.roadblocks + excerpt.roadblock_connectors}
    assert [b.id for b in graph.block_successors[block["1"]]] == ["12"]
    assert [b.id for b in graph.block_successors[block["12"]]] == ["2"]
    assert [b.id for b in graph.block_predecessors[block["2"]]] == ["12"]
    assert [lane.id for lane in graph.interior[block["23"]]] == ["230"]
    lanes = {lane.id: lane for lane in excerpt.lanes + excerpt.lane_connectors}
    assert [lane.id for lane in graph.lane_successors[lanes["10"]]] == ["120"]
    assert [lane.id for lane in graph.lane_successors[lanes["120"]]] == ["20"]
    assert graph.is_connector(block["12"]) and not graph.is_connector(block["1"])
    # The excerpt's roadblock wins over a roadblock connector of the same id (nuPlan's lookup order).
    assert graph.block("2") is block["2"] and graph.block("99") is None


def test_route_keeps_first_occurrences_and_lists_lanes_of_its_blocks() -> None:
    graph = build_road_graph(_straight_road())
    route = load_route(graph, ["1", "12", "1", "2"], "token")
    assert route.block_ids == ("1", "12", "2")
    assert route.lane_ids == ("10", "120", "20")


def test_a_route_roadblock_missing_from_the_excerpt_is_an_error_naming_it() -> None:
    with pytest.raises(RouteError, match="'7'"):
        load_route(build_road_graph(_straight_road()), ["1", "7"], "token")


def test_a_lane_with_a_zero_length_baseline_fails_only_where_it_is_read() -> None:
    """nuPlan's discrete path asserts on a zero-length polyline: the devkit cannot cache such a scene."""
    road = _straight_road()
    degenerate = _lane("20", "2", [[15, 0], [15, 0]])  # the lane of roadblock 2: both vertices equal
    excerpt = MapExcerpt(
        lanes=(road.lanes[0], degenerate, road.lanes[2]),
        lane_connectors=road.lane_connectors,
        roadblocks=road.roadblocks,
        roadblock_connectors=road.roadblock_connectors,
    )
    graph = build_road_graph(excerpt)
    route = load_route(graph, ["1", "12", "2", "23", "3"], "token")
    corrected = correct_route(graph, excerpt, route, (5.0, 0.0, 0.0), "token")  # roadblock 1: not read
    assert corrected.block_ids == route.block_ids
    with pytest.raises(RouteError, match="lane 20: its baseline has zero length"):
        correct_route(
            graph, excerpt, route, (15.0, 0.0, 0.0), "token"
        )  # roadblock 2: its lane is a candidate


def test_a_missing_connector_is_inserted_and_a_route_starting_behind_the_ego_is_kept() -> None:
    excerpt = _straight_road()
    graph = build_road_graph(excerpt)
    route = load_route(graph, ["1", "2", "23", "3"], "token")
    corrected = correct_route(graph, excerpt, route, (15.0, 0.0, 0.0), "token")
    assert corrected.block_ids == ("1", "12", "2", "23", "3")


def test_an_ego_behind_the_route_gets_the_blocks_up_to_the_route_prepended() -> None:
    excerpt = _straight_road()
    graph = build_road_graph(excerpt)
    route = load_route(graph, ["3"], "token")
    corrected = correct_route(graph, excerpt, route, (5.0, 0.0, 0.0), "token")
    assert corrected.block_ids == ("1", "12", "2", "23", "3")


def test_an_ego_ahead_of_the_route_start_drops_the_route_up_to_the_block_reached() -> None:
    # The ego is on roadblock 2, which is not on the route [1, 12, 3] (connector 23 missing, 2 absent):
    # the backward search from 1 cannot reach 2, the forward search from 2 reaches 3 within the first 3
    # route blocks, so the route becomes [2, 23, 3].
    excerpt = _straight_road()
    graph = build_road_graph(excerpt)
    route = load_route(graph, ["1", "12", "3"], "token")
    corrected = correct_route(graph, excerpt, route, (15.0, 0.0, 0.0), "token")
    assert corrected.block_ids == ("2", "23", "3")


def test_the_route_is_cut_before_a_connector_overlapping_an_earlier_one() -> None:
    excerpt = _straight_road()
    looped = MapExcerpt(
        lanes=excerpt.lanes,
        lane_connectors=excerpt.lane_connectors,
        roadblocks=excerpt.roadblocks,
        # Connector 23 overlaps connector 12 by 2 m^2 (more than 1 m^2): a loop.
        roadblock_connectors=(
            excerpt.roadblock_connectors[0],
            _connector("23", "2", "3", shapely.box(10, -2, 11, 2)),
        ),
    )
    graph = build_road_graph(looped)
    route = load_route(graph, ["1", "12", "2", "23", "3"], "token")
    assert correct_route(graph, looped, route, (5.0, 0.0, 0.0), "token").block_ids == ("1", "12", "2")


def _devkit_bfs(
    successors: dict[str, list[str]], start: str, targets: set[str], max_depth: int
) -> list[str] | None:
    """The devkit's queue as written: every walk kept, a depth marker, parents keyed by (id, depth)."""
    queue: deque[str | None] = deque([start, None])
    parents: dict[tuple[str, int], str | None] = {(start, 1): None}
    depth = 1
    while queue:
        current = queue.popleft()
        if depth > max_depth:
            return None
        if current is None:
            depth += 1
            queue.append(None)
            if queue[0] is None:
                return None
            continue
        if current in targets:
            path, level = [current], depth
            while (parent := parents[(path[-1], level)]) is not None:
                path.append(parent)
                level -= 1
            return path[::-1]
        for successor in successors[current]:
            queue.append(successor)
            parents[(successor, depth + 1)] = current
    return None


@settings(max_examples=200, deadline=None)
@given(
    edges=st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6)), max_size=16),
    target=st.integers(0, 6),
    max_depth=st.integers(1, 7),
)
def test_level_search_finds_the_devkit_queue_path(
    edges: list[tuple[int, int]], target: int, max_depth: int
) -> None:
    """The collapsed levels give the path of the devkit's exponential walk queue, parents included."""
    nodes = [str(i) for i in range(7)]
    blocks = {node: _block(node) for node in nodes}
    connectors = [_connector(f"c{k}", str(a), str(b)) for k, (a, b) in enumerate(edges)]
    # Roadblock -> connector -> roadblock: map the block graph onto the excerpt's two layers.
    excerpt = MapExcerpt(
        lanes=(),
        lane_connectors=(),
        roadblocks=tuple(blocks.values()),
        roadblock_connectors=tuple(connectors),
    )
    graph = build_road_graph(excerpt)
    doubled = {node: [f"c{k}" for k, (a, _) in enumerate(edges) if str(a) == node] for node in nodes}
    doubled |= {f"c{k}": [str(b)] for k, (_, b) in enumerate(edges)}
    expected = _devkit_bfs(doubled, "0", {str(target)}, 2 * max_depth)
    found = search_blocks(graph, blocks["0"], [str(target)], 2 * max_depth, forward=True)
    assert (None if found is None else [block.id for block in found]) == expected


def test_dijkstra_prefers_the_shorter_branch_and_the_first_queued_on_ties() -> None:
    # Lane a forks into connectors x (to b, 10 m) and y (to c, 10 m); b and c both lie in roadblock T.
    lanes = (
        _lane("1", "A", [[0, 0], [10, 0]]),
        _lane("2", "T", [[12, 1], [22, 1]]),
        _lane("3", "T", [[12, -1], [22, -1]]),
    )
    connectors = (
        _lane("4", "AT", [[10, 0], [12, 1]], "1", "2"),
        _lane("5", "AT2", [[10, 0], [12, -1]], "1", "3"),
    )
    blocks = (_block("A"), _block("T"))
    block_connectors = (_connector("AT", "A", "T"), _connector("AT2", "A", "T"))
    excerpt = MapExcerpt(
        lanes=lanes, lane_connectors=connectors, roadblocks=blocks, roadblock_connectors=block_connectors
    )
    graph = build_road_graph(excerpt)
    route = Route(
        blocks=(blocks[0], block_connectors[0], block_connectors[1], blocks[1]), lanes=lanes + connectors
    )
    # Equal lengths: the connector queued first (layer order) wins.
    assert [lane.id for lane in centerline_lanes(graph, route, lanes[0])] == ["1", "4", "2"]
    longer = (_lane("4", "AT", [[10, 0], [11, 3], [12, 1]], "1", "2"), connectors[1])
    graph = build_road_graph(
        MapExcerpt(
            lanes=lanes, lane_connectors=longer, roadblocks=blocks, roadblock_connectors=block_connectors
        )
    )
    route = Route(blocks=route.blocks, lanes=lanes + longer)
    assert [lane.id for lane in centerline_lanes(graph, route, lanes[0])] == ["1", "5", "3"]


def test_dijkstra_without_a_path_ends_at_the_cheapest_deepest_lane() -> None:
    excerpt = _straight_road()
    graph = build_road_graph(excerpt)
    lanes = {lane.id: lane for lane in excerpt.lanes + excerpt.lane_connectors}
    # The goal block 3 is unreachable because connector lane 230 is not on the route.
    route = Route(blocks=excerpt.roadblocks, lanes=tuple(lanes[i] for i in ("10", "120", "20", "30")))
    assert [lane.id for lane in centerline_lanes(graph, route, lanes["10"])] == ["10", "120", "20"]


def test_every_pair_of_search_depths_is_explored_without_walk_explosion() -> None:
    # A ladder of 12 diamonds has 2**12 walks; the level search stays linear.
    blocks = [_block(str(i)) for i in range(25)]
    connectors = []
    for i in range(0, 24, 2):
        connectors += [_connector(f"u{i}", str(i), str(i + 1)), _connector(f"d{i}", str(i), str(i + 1))]
        connectors += [_connector(f"n{i}", str(i + 1), str(i + 2))]
    graph = build_road_graph(
        MapExcerpt(
            lanes=(), lane_connectors=(), roadblocks=tuple(blocks), roadblock_connectors=tuple(connectors)
        )
    )
    path = search_blocks(graph, blocks[0], ["24"], 60, forward=True)
    assert path is not None and [b.id for b in path][:3] == [
        "0",
        "d0",
        "1",
    ]  # last-written parent: the later walk
    assert list(itertools.islice((b.id for b in path), 0, None, 2))[-1] == "24"
