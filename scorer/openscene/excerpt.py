"""Cut the map excerpt of one scene out of the full map (scene-format.md, "Map excerpt").

An excerpt holds every object meeting the square of half-side 100 m around the ego box centre or a
small square around a current vehicle's centre (where v2's reactive traffic looks for its lane), and
the roadblock-graph neighbourhood the engine's route repair can reach: the route, 15 steps back
and 30 forward from it, and 30 forward from the blocks the ego may start in. Every block comes with
all its lanes or lane connectors, every layer keeps map table order, and ids are unchanged.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely

from scorer.geometry import ego_center
from scorer.openscene.frames import EgoPose
from scorer.openscene.gpkg import Layer, MapFormatError, MapTables, layer_rows
from scorer.scene import Area, Lane, MapExcerpt, Roadblock

DRIVABLE_HALF_SIDE_M = 100.0  # the engine's drivable-area square around the ego centre
STARTING_HALF_SIDE_M = 1.0  # the engine's starting-roadblock square around the rear axle
EDGE_MARGIN_M = (
    2.0  # widens both squares so float rounding at an edge never drops an object the engine selects
)
ROUTE_BACKWARD_STEPS = 15
ROUTE_FORWARD_STEPS = 30
AREA_TABLES = ("intersections", "carpark_areas", "drivable_areas", "crosswalks", "walkways")


@dataclass(frozen=True, eq=False)
class Excerpt:
    """A map excerpt and what was lost converting it (holes, extra polygon parts)."""

    map: MapExcerpt
    warnings: tuple[str, ...]


def build_excerpt(
    tables: MapTables,
    pose: EgoPose,
    route_ids: Sequence[str],
    vehicles: Sequence[tuple[float, float]] = (),
) -> Excerpt:
    """Return the excerpt of `tables` a scene with this current ego pose and route needs; `vehicles` are the
    box centres of the current frame's vehicles, whose lanes the reactive traffic drives on."""
    center_x, center_y = ego_center(pose.x, pose.y, pose.heading)
    # v2's reactive traffic finds each current vehicle's lane or connector (and tells parked vehicles by
    # lanes and intersections) at its centre, however far from the ego: a small square there joins the area.
    area = shapely.union_all(
        [
            _square(float(center_x), float(center_y), DRIVABLE_HALF_SIDE_M + EDGE_MARGIN_M),
            *(_square(x, y, EDGE_MARGIN_M) for x, y in vehicles),
        ]
    )
    starting_square = _square(pose.x, pose.y, STARTING_HALF_SIDE_M + EDGE_MARGIN_M)
    rear_axle = shapely.Point(pose.x, pose.y)

    roadblocks = _ids(tables.roadblocks, tables.roadblocks.rows_intersecting(area))
    connectors = _ids(tables.roadblock_connectors, tables.roadblock_connectors.rows_intersecting(area))
    # Lanes and connectors in the area bring their parents (and so all their siblings).
    roadblocks |= _parents(
        tables.lanes, _ids(tables.lanes, tables.lanes.rows_intersecting(area)), "lane_group_fid"
    )
    connectors |= _parents(
        tables.lane_connectors,
        _ids(tables.connector_polygons, tables.connector_polygons.rows_intersecting(area)),
        "lane_group_connector_fid",
    )

    route = [_route_block(tables, block_id) for block_id in dict.fromkeys(route_ids)]
    starting = [
        *_ids(tables.roadblocks, tables.roadblocks.rows_intersecting(starting_square)),
        *_ids(tables.roadblock_connectors, tables.roadblock_connectors.rows_intersecting(starting_square)),
        *(
            layer.ids[row]
            for layer in (tables.roadblocks, tables.roadblock_connectors)
            if (row := layer.nearest_row(rear_axle)) is not None
        ),
    ]
    graph = _RoadblockGraph(tables)
    reachable = (
        graph.reachable(route, ROUTE_BACKWARD_STEPS, graph.predecessors)
        | graph.reachable(route, ROUTE_FORWARD_STEPS, graph.successors)
        | graph.reachable(starting, ROUTE_FORWARD_STEPS, graph.successors)
    )
    roadblocks |= reachable & set(tables.roadblocks.row_of)
    connectors |= reachable & set(tables.roadblock_connectors.row_of)

    builder = _ExcerptBuilder(tables)
    lanes = [lane for block in roadblocks for lane in tables.roadblock_lanes.get(block, [])]
    lane_connectors = [
        lane for block in connectors for lane in tables.roadblock_connector_lanes.get(block, [])
    ]
    excerpt = MapExcerpt(
        lanes=tuple(builder.lane(row) for row in layer_rows(tables.lanes, lanes)),
        lane_connectors=tuple(
            builder.lane_connector(row) for row in layer_rows(tables.lane_connectors, lane_connectors)
        ),
        roadblocks=tuple(builder.roadblock(row) for row in layer_rows(tables.roadblocks, roadblocks)),
        roadblock_connectors=tuple(
            builder.roadblock_connector(row) for row in layer_rows(tables.roadblock_connectors, connectors)
        ),
        **{
            name: tuple(
                builder.area(getattr(tables, name), row)
                for row in getattr(tables, name).rows_intersecting(area)
            )
            for name in AREA_TABLES
        },
    )
    return Excerpt(excerpt, tuple(builder.warnings))


def _square(x: float, y: float, half_side: float) -> shapely.Polygon:
    return shapely.box(x - half_side, y - half_side, x + half_side, y + half_side)


def _ids(layer: Layer, rows: Iterable[int]) -> set[str]:
    return {layer.ids[row] for row in rows}


def _parents(layer: Layer, ids: Iterable[str], column: str) -> set[str]:
    rows = (layer.row_of[object_id] for object_id in ids if object_id in layer.row_of)
    return {parent for row in rows if (parent := layer.attributes[column][row]) is not None}


def _attribute(layer: Layer, object_id: str, column: str) -> str:
    value = layer.attributes[column][layer.row_of[object_id]]
    if value is None:
        raise MapFormatError(f"{layer.table} {object_id}: {column} is empty")
    return value


def _route_block(tables: MapTables, block_id: str) -> str:
    """Check a route id as the devkit looks it up: a roadblock, else a roadblock connector."""
    if block_id not in tables.roadblocks.row_of and block_id not in tables.roadblock_connectors.row_of:
        raise MapFormatError(
            f"route roadblock {block_id} is neither in lane_groups_polygons nor in lane_group_connectors of {tables.path}"
        )
    return block_id


class _RoadblockGraph:
    """Roadblocks and roadblock connectors alternate: R -> K when K leaves R, K -> R' when K enters R'."""

    def __init__(self, tables: MapTables) -> None:
        self.tables = tables

    def successors(self, block_id: str) -> list[str]:
        if block_id in self.tables.roadblocks.row_of:
            return self.tables.roadblock_outgoing.get(block_id, [])
        return self._ends(block_id, "to_lane_group_fid")

    def predecessors(self, block_id: str) -> list[str]:
        if block_id in self.tables.roadblocks.row_of:
            return self.tables.roadblock_incoming.get(block_id, [])
        return self._ends(block_id, "from_lane_group_fid")

    def _ends(self, connector_id: str, column: str) -> list[str]:
        layer = self.tables.roadblock_connectors
        row = layer.row_of.get(connector_id)
        end = None if row is None else layer.attributes[column][row]
        return [] if end is None else [end]

    @staticmethod
    def reachable(starts: Iterable[str], steps: int, neighbours: Callable[[str], list[str]]) -> set[str]:
        """Return the blocks within `steps` edges of any start (starts included)."""
        depth = dict.fromkeys(starts, 0)
        queue = deque(depth)
        while queue:
            block = queue.popleft()
            if depth[block] == steps:
                continue
            for neighbour in neighbours(block):
                if neighbour not in depth:
                    depth[neighbour] = depth[block] + 1
                    queue.append(neighbour)
        return set(depth)


class _ExcerptBuilder:
    """Scene-model objects from map rows; collects what the outer-ring polygons of format v1 lose."""

    def __init__(self, tables: MapTables) -> None:
        self.tables = tables
        self.warnings: list[str] = []

    def lane(self, row: int) -> Lane:
        layer = self.tables.lanes
        lane_id = layer.ids[row]
        return Lane(
            id=lane_id,
            polygon=self.polygon(layer.geometries[row], f"lanes {lane_id}"),
            roadblock=_attribute(layer, lane_id, "lane_group_fid"),
            baseline=self.baseline(lane_id, "lane"),
            speed_limit_mps=layer.attributes["speed_limit_mps"][row],
            incoming=tuple(self.tables.lane_incoming.get(lane_id, [])),
            outgoing=tuple(self.tables.lane_outgoing.get(lane_id, [])),
        )

    def lane_connector(self, row: int) -> Lane:
        layer = self.tables.lane_connectors
        connector_id = layer.ids[row]
        polygon_row = self.tables.connector_polygons.row_of.get(connector_id)
        if polygon_row is None:
            raise MapFormatError(
                f"lane connector {connector_id} has no polygon in gen_lane_connectors_scaled_width_polygons"
            )
        return Lane(
            id=connector_id,
            polygon=self.polygon(
                self.tables.connector_polygons.geometries[polygon_row], f"lane_connectors {connector_id}"
            ),
            roadblock=_attribute(layer, connector_id, "lane_group_connector_fid"),
            baseline=self.baseline(connector_id, "lane connector"),
            speed_limit_mps=layer.attributes["speed_limit_mps"][row],
            incoming=(_attribute(layer, connector_id, "exit_lane_fid"),),
            outgoing=(_attribute(layer, connector_id, "entry_lane_fid"),),
        )

    def roadblock(self, row: int) -> Roadblock:
        block_id = self.tables.roadblocks.ids[row]
        return Roadblock(
            id=block_id,
            polygon=self.polygon(self.tables.roadblocks.geometries[row], f"roadblocks {block_id}"),
            incoming=tuple(self.tables.roadblock_incoming.get(block_id, [])),
            outgoing=tuple(self.tables.roadblock_outgoing.get(block_id, [])),
            lanes=tuple(self.tables.roadblock_lanes.get(block_id, [])),
        )

    def roadblock_connector(self, row: int) -> Roadblock:
        layer = self.tables.roadblock_connectors
        connector_id = layer.ids[row]
        return Roadblock(
            id=connector_id,
            polygon=self.polygon(layer.geometries[row], f"roadblock_connectors {connector_id}"),
            incoming=(_attribute(layer, connector_id, "from_lane_group_fid"),),
            outgoing=(_attribute(layer, connector_id, "to_lane_group_fid"),),
            lanes=tuple(self.tables.roadblock_connector_lanes.get(connector_id, [])),
        )

    def area(self, layer: Layer, row: int) -> Area:
        return Area(
            id=layer.ids[row], polygon=self.polygon(layer.geometries[row], f"{layer.table} {layer.ids[row]}")
        )

    def baseline(self, lane_id: str, kind: str) -> np.ndarray:
        try:
            return self.tables.baselines[lane_id]
        except KeyError:
            raise MapFormatError(f"{kind} {lane_id} has no baseline path in baseline_paths") from None

    def polygon(self, geometry: Any, where: str) -> shapely.Polygon:
        """Return the outer ring as the scene loader builds it (the ring's closing vertex is implicit)."""
        if isinstance(geometry, shapely.MultiPolygon):
            parts = list(geometry.geoms)
            if len(parts) > 1:
                self.warnings.append(f"{where}: {len(parts)} polygon parts; only the largest is kept")
            geometry = max(parts, key=lambda part: part.area)
        if not isinstance(geometry, shapely.Polygon) or geometry.is_empty:
            raise MapFormatError(
                f"{where}: expected a polygon, got {getattr(geometry, 'geom_type', geometry)!r}"
            )
        if geometry.interiors:
            self.warnings.append(
                f"{where}: {len(geometry.interiors)} hole(s) dropped (format v1 stores outer rings)"
            )
        return shapely.polygons(shapely.get_coordinates(geometry.exterior)[:-1])


def excerpt_to_json(excerpt: MapExcerpt) -> dict[str, list[dict[str, Any]]]:
    """Return the `map` object of a scene file."""

    def ring(polygon: shapely.Polygon) -> list[list[float]]:
        return shapely.get_coordinates(polygon.exterior)[:-1].tolist()

    def lane(item: Lane) -> dict[str, Any]:
        return {
            "id": item.id,
            "polygon": ring(item.polygon),
            "roadblock": item.roadblock,
            "baseline": np.asarray(item.baseline, dtype=np.float64).tolist(),
            "speed_limit_mps": item.speed_limit_mps,
            "incoming": list(item.incoming),
            "outgoing": list(item.outgoing),
        }

    def block(item: Roadblock) -> dict[str, Any]:
        return {
            "id": item.id,
            "polygon": ring(item.polygon),
            "incoming": list(item.incoming),
            "outgoing": list(item.outgoing),
            "lanes": list(item.lanes),
        }

    return {
        "lanes": [lane(item) for item in excerpt.lanes],
        "lane_connectors": [lane(item) for item in excerpt.lane_connectors],
        "roadblocks": [block(item) for item in excerpt.roadblocks],
        "roadblock_connectors": [block(item) for item in excerpt.roadblock_connectors],
        **{
            name: [{"id": area.id, "polygon": ring(area.polygon)} for area in getattr(excerpt, name)]
            for name in AREA_TABLES
        },
    }
