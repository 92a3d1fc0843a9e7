"""The drivable-area map around the ego: the map polygons the scorer tests ego points against.

As `PDMDrivableMap.from_simulation` with nuPlan's `get_proximal_map_objects`: every roadblock,
roadblock connector, intersection and car park whose polygon meets the axis-aligned square of
half-side 100 m around the ego *box centre* (touching counts). The polygon list is, in this order: the
roadblocks; the lanes of each of those roadblocks, then the lane connectors of each roadblock
connector (connector polygons themselves are left out); the intersections; the car parks. Each layer
keeps the order of the excerpt's layer list, as nuPlan's map tables do (docs/engine.md, "Drivable-area map").
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import shapely

from scorer.geometry import BoolArray, FloatArray, IntArray, ego_center
from scorer.scene import Lane, Scene

MAP_RADIUS = 100.0  # half-side of the proximity square, m
ROADBLOCK = "ROADBLOCK"
LANE = "LANE"
LANE_CONNECTOR = "LANE_CONNECTOR"
INTERSECTION = "INTERSECTION"
CARPARK_AREA = "CARPARK_AREA"
DRIVABLE_AREA = "DRIVABLE_AREA"  # never built (the devkit does not query it), but counted as drivable
DRIVABLE_TYPES = (ROADBLOCK, INTERSECTION, DRIVABLE_AREA, CARPARK_AREA)
LANE_TYPES = (LANE, LANE_CONNECTOR)


# Polygons' exterior rings (closed) end to end (N, 2), and each ring's coordinate count (m,).
Outlines = tuple[FloatArray, IntArray]


def polygon_outlines(polygons: Iterable[shapely.Polygon]) -> Outlines:
    """Return the exterior coordinates of polygons and each polygon's coordinate count (int64)."""
    rings = shapely.get_exterior_ring(np.asarray(list(polygons), dtype=object))
    return shapely.get_coordinates(rings), shapely.get_num_coordinates(rings).astype(np.int64)


def outline_polygons(outlines: Outlines) -> npt.NDArray[np.object_]:
    """Return one single-ring polygon per outline, in one call (faster than rings, then polygons)."""
    coords, counts = outlines
    if not len(counts):
        return np.empty(0, dtype=object)
    ring_offsets = np.concatenate([[0], np.cumsum(counts)])
    polygon_offsets = np.arange(len(counts) + 1)
    return shapely.from_ragged_array(shapely.GeometryType.POLYGON, coords, (ring_offsets, polygon_offsets))


@dataclass(frozen=True, eq=False)
class DrivableMap:
    """Map polygons with their map object ids and nuPlan layer names, in the devkit's order.

    Made from a scene's polygons (`built`) or from their outlines as a metric cache stores them (`stored`):
    scoring tests points against a few of a map's polygons only, and a batch builds just those
    (`MapBatch.polygons_at`); each form is derived from the other where read.
    """

    tokens: tuple[str, ...]
    types: tuple[str, ...]
    built: npt.NDArray[np.object_] | None = None  # (m,) shapely Polygons
    stored: Outlines | None = None

    def __post_init__(self) -> None:
        if (self.built is None) == (self.stored is None):
            raise ValueError("a drivable map is made from its polygons or from their outlines")

    @cached_property
    def polygons(self) -> npt.NDArray[np.object_]:
        """The polygons (m,)."""
        return self.built if self.built is not None else outline_polygons(self.outlines)

    @cached_property
    def outlines(self) -> Outlines:
        """The polygons' exterior rings (`polygon_outlines`)."""
        if self.stored is not None:
            return self.stored
        return polygon_outlines(self.polygons)


class MapBatch(NamedTuple):
    """The drivable-area maps of several scene tokens side by side, with each polygon's role for the scorer.

    Polygon j of token b is entry start[b] + j.
    """

    polygons: npt.NDArray[np.object_]  # (M,) prepared; None where not built yet (`polygons_at`)
    outlines: Outlines  # (N, 2), (M,)
    bounds: FloatArray  # (M, 4)
    is_lane: BoolArray  # lane or lane connector
    is_drivable: BoolArray  # roadblock, intersection, car park (lanes are not drivable polygons)
    is_intersection: BoolArray
    is_route: BoolArray  # a lane of the token's route
    start: IntArray  # (B,)
    counts: IntArray  # (B,)

    @classmethod
    def of(cls, maps: Sequence[DrivableMap], route_lane_ids: Sequence[Collection[str]]) -> "MapBatch":
        """Return the batch of `maps`, each with its token's route lane ids, in one pass over their polygons."""
        polygon_counts = np.array([len(drivable_map.tokens) for drivable_map in maps], dtype=np.intp)
        # A map read from a cache brings outlines only: its polygons are built where a test reads them.
        polygons = np.concatenate(
            [
                drivable_map.built
                if drivable_map.built is not None
                else np.full(len(drivable_map.tokens), None)
                for drivable_map in maps
            ]
        )
        # Prepared in place (a prepared one is left as is): the same results, faster point-in-polygon tests.
        shapely.prepare(polygons)
        coords = np.concatenate([drivable_map.outlines[0] for drivable_map in maps])
        vertex_counts = np.concatenate([drivable_map.outlines[1] for drivable_map in maps])
        types = [kind for drivable_map in maps for kind in drivable_map.types]
        routes = [set(route) for route in route_lane_ids]
        listed = [token in route for m, route in zip(maps, routes, strict=True) for token in m.tokens]
        is_lane = np.array([kind in LANE_TYPES for kind in types], dtype=bool)
        return cls(
            polygons=polygons,
            outlines=(coords, vertex_counts),
            bounds=_outline_bounds(coords, vertex_counts),
            is_lane=is_lane,
            is_drivable=np.array([kind in DRIVABLE_TYPES for kind in types], dtype=bool),
            is_intersection=np.array([kind == INTERSECTION for kind in types], dtype=bool),
            is_route=is_lane & np.array(listed, dtype=bool),
            start=np.cumsum(polygon_counts) - polygon_counts,
            counts=polygon_counts,
        )

    def polygons_at(self, index: IntArray) -> npt.NDArray[np.object_]:
        """Return the polygons at `index`, building and preparing those not built yet from their outlines."""
        wanted = np.zeros(len(self.polygons), dtype=bool)
        wanted[index] = True
        missing = np.flatnonzero(wanted & shapely.is_missing(self.polygons))
        if len(missing):
            coords, vertex_counts = self.outlines
            first = np.cumsum(vertex_counts) - vertex_counts
            sizes = vertex_counts[missing]
            rows = np.repeat(first[missing] - np.cumsum(sizes) + sizes, sizes) + np.arange(sizes.sum())
            built = outline_polygons((coords[rows], sizes))
            shapely.prepare(built)
            self.polygons[missing] = built
        return self.polygons[index]


def _outline_bounds(coords: FloatArray, counts: IntArray) -> FloatArray:
    """Return each outline's bounding box (M, 4), xmin, ymin, xmax, ymax: GEOS's envelope, the minima and maxima
    of the coordinates, which round nothing."""
    if not len(counts):
        return np.empty((0, 4))
    first = np.cumsum(counts) - counts
    x, y = np.ascontiguousarray(coords[:, 0]), np.ascontiguousarray(coords[:, 1])
    return np.stack(
        [
            np.minimum.reduceat(x, first),
            np.minimum.reduceat(y, first),
            np.maximum.reduceat(x, first),
            np.maximum.reduceat(y, first),
        ],
        axis=-1,
    )


def proximal_mask(polygons: npt.ArrayLike, x: float, y: float, half_side: float) -> BoolArray:
    """Return which polygons meet the axis-aligned square of `half_side` around (x, y); touching counts."""
    square = shapely.box(x - half_side, y - half_side, x + half_side, y + half_side)
    return np.asarray(shapely.intersects(np.asarray(polygons, dtype=object), square), dtype=bool)


def _interior_edges(blocks: Sequence[str], edges: Sequence[Lane]) -> list[Lane]:
    """Return the lanes (or lane connectors) of each block in turn, each block's in layer order."""
    by_block: dict[str, list[Lane]] = {}
    for edge in edges:
        by_block.setdefault(edge.roadblock, []).append(edge)
    return [edge for block in blocks for edge in by_block.get(block, [])]


def build_drivable_map(scene: Scene) -> DrivableMap:
    """Return the drivable-area map around the ego box centre of the current frame.

    See docs/engine.md, "Drivable-area map".
    """
    ego = scene.current_frame.ego
    center_x, center_y = (float(value) for value in ego_center(ego.x, ego.y, ego.heading))
    excerpt = scene.map

    def near(layer: Sequence[object]) -> list:
        polygons = [item.polygon for item in layer]  # type: ignore[attr-defined]
        if not polygons:
            return []
        return [
            item
            for item, hit in zip(layer, proximal_mask(polygons, center_x, center_y, MAP_RADIUS), strict=True)
            if hit
        ]

    roadblocks = near(excerpt.roadblocks)
    connectors = near(excerpt.roadblock_connectors)
    lanes = _interior_edges([block.id for block in roadblocks], excerpt.lanes)
    lane_connectors = _interior_edges([block.id for block in connectors], excerpt.lane_connectors)
    layers = (
        (ROADBLOCK, roadblocks),
        (LANE, lanes),
        (LANE_CONNECTOR, lane_connectors),
        (INTERSECTION, near(excerpt.intersections)),
        (CARPARK_AREA, near(excerpt.carpark_areas)),
    )
    items = [(kind, item) for kind, layer in layers for item in layer]
    polygons = np.empty(len(items), dtype=object)
    polygons[:] = [item.polygon for _, item in items]
    return DrivableMap(
        tokens=tuple(item.id for _, item in items),
        types=tuple(kind for kind, _ in items),
        built=polygons,
    )
