"""GEOS on one geometry at a time, as the IDM's loop asks it (docs/engine.md, "Reactive traffic: speed").

Each function is the shapely call the devkit makes (named beside it), made through shapely's compiled ufuncs
(`shapely.lib`, which the public functions call with these very arguments): the loop makes a few hundred of
them per simulation on single geometries, where the public functions' Python (argument checks, the
deprecation and multithreading wrappers, array conversions) costs about as much as GEOS itself. Same GEOS
call, same arguments: the same coordinates. shapely is pinned (2.2.0), so these signatures are its.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import shapely
from shapely import lib

from scorer.geometry import FloatArray

_HANDLE_NAN_ALLOW = np.intc(0)  # shapely's default `handle_nan="allow"`
_NO_HOLES = np.empty((0,), dtype=object)
_QUAD_SEGS = np.intc(8)  # shapely.buffer's defaults, as the devkit calls it
_CAP_FLAT = np.intc(shapely.BufferCapStyle.flat)
_JOIN_ROUND = np.intc(shapely.BufferJoinStyle.round)
_MITRE_LIMIT = 5.0
_SINGLE_SIDED = np.bool_(False)
_COLLECTION = np.intc(shapely.GeometryType.GEOMETRYCOLLECTION)


def polygon(corners: Sequence[tuple[float, float]]) -> shapely.Polygon:
    """Return `shapely.polygons(np.array(corners))`: the ring closed, no holes."""
    return lib.polygons(lib.linearrings(np.array(corners), _HANDLE_NAN_ALLOW), _NO_HOLES)


def line(points: FloatArray) -> shapely.LineString:
    """Return `shapely.linestrings(points)`."""
    return lib.linestrings(points, _HANDLE_NAN_ALLOW)


def flat_buffer(geometry: shapely.Geometry, distance: float) -> shapely.Geometry:
    """Return `shapely.buffer(geometry, distance, cap_style="flat")`."""
    return lib.buffer(geometry, distance, _QUAD_SEGS, _CAP_FLAT, _JOIN_ROUND, _MITRE_LIMIT, _SINGLE_SIDED)


def union(first: shapely.Geometry, second: shapely.Geometry) -> shapely.Geometry:
    """Return `shapely.union_all([first, second])` (GEOS's unary union of the collection of both)."""
    geometries = np.empty(2, dtype=object)
    geometries[0], geometries[1] = first, second
    return lib.unary_union(lib.create_collection(geometries, _COLLECTION))


def simplify(geometry: shapely.Geometry, tolerance: float) -> shapely.Geometry:
    """Return `shapely.simplify(geometry, tolerance, preserve_topology=True)`."""
    return lib.simplify_preserve_topology(geometry, tolerance)


def equals_exactly(first: shapely.Geometry, second: shapely.Geometry) -> bool:
    """Return `shapely.equals_exact(first, second, tolerance=0.0)`."""
    return bool(lib.equals_exact(first, second, 0.0))


def intersects(first: shapely.Geometry, second: shapely.Geometry) -> bool:
    """Return `shapely.intersects(first, second)`."""
    return bool(lib.intersects(first, second))


def distance(first: shapely.Geometry, second: shapely.Geometry) -> float:
    """Return `shapely.distance(first, second)`."""
    return float(lib.distance(first, second))
