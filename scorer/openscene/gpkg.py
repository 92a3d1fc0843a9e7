"""Read the nuPlan map GeoPackage layers NAVSIM v1.x uses, in the map's own projected system (upstream-formats.md 4).

Plain sqlite3 plus shapely: geometry blobs are GeoPackage headers followed by WKB. Each layer is
reprojected from its registered CRS to the `projectedCoordSystem` of the `meta` table with pyproj,
as nuPlan's maps DB does with geopandas (`to_crs`, skipped when both systems are the same).
Rows keep table order (feature id order): the devkit's graph tie-breaks follow it.
"""

from __future__ import annotations

import json
import math
import sqlite3
from collections import defaultdict
from collections.abc import Collection
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pyproj
import shapely

from scorer.geometry import FloatArray

MAP_LOCATIONS = ("sg-one-north", "us-ma-boston", "us-nv-las-vegas-strip", "us-pa-pittsburgh-hazelwood")
LEGACY_MAP_NAMES = {"las_vegas": "us-nv-las-vegas-strip"}  # NavSimScenario's only alias
MAPS_VERSION_FILE = "nuplan-maps-v1.0.json"  # NAVSIM hard-codes map version "nuplan-maps-v1.0"
_ENVELOPE_BYTES = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}


class MapFormatError(ValueError):
    """A map file or location is unusable; the message names the file, table or object."""


def map_location(name: str) -> str:
    """Return the nuPlan map location of a log's `map_location` value."""
    location = LEGACY_MAP_NAMES.get(name, name)
    if location not in MAP_LOCATIONS:
        raise MapFormatError(f"unknown map location {name!r}; expected one of {MAP_LOCATIONS}")
    return location


def gpkg_path(maps_dir: Path, location: str) -> Path:
    """Return `<maps>/<location>/<version>/map.gpkg`, the version read from nuplan-maps-v1.0.json when present."""
    version_file = maps_dir / MAPS_VERSION_FILE
    if version_file.is_file():
        try:
            version = json.loads(version_file.read_text())[location]["version"]
        except (KeyError, TypeError, json.JSONDecodeError) as error:
            raise MapFormatError(f"{version_file}: no version for {location} ({error})") from None
        path = maps_dir / location / str(version) / "map.gpkg"
        if not path.is_file():
            raise MapFormatError(f"{path}: map file missing (version {version} from {version_file})")
        return path
    candidates = sorted((maps_dir / location).glob("*/map.gpkg"))
    if len(candidates) != 1:
        raise MapFormatError(
            f"{maps_dir / location}: expected one <version>/map.gpkg without {MAPS_VERSION_FILE}, found {len(candidates)}"
        )
    return candidates[0]


@dataclass(frozen=True, eq=False)
class Layer:
    """One vector table: string feature ids, projected geometries and attribute columns, in table order."""

    table: str
    ids: tuple[str, ...]
    geometries: np.ndarray  # (n,) object, shapely geometries in the projected CRS
    attributes: dict[str, tuple[Any, ...]]

    @cached_property
    def row_of(self) -> dict[str, int]:
        """Return id -> row."""
        return {object_id: row for row, object_id in enumerate(self.ids)}

    @cached_property
    def tree(self) -> shapely.STRtree:
        """Return the spatial index of the geometries."""
        return shapely.STRtree(self.geometries)

    def rows_intersecting(self, area: shapely.Geometry) -> np.ndarray:
        """Return the sorted rows whose geometry intersects `area` (touching counts)."""
        return np.sort(self.tree.query(area, predicate="intersects"))

    def nearest_row(self, point: shapely.Point) -> int | None:
        """Return the row of the geometry nearest to `point` (None for an empty layer)."""
        return None if not self.ids else int(self.tree.nearest(point))


@dataclass(frozen=True, eq=False)
class MapTables:
    """The layers of one map location and the graph relations derived from their key columns."""

    location: str
    path: Path
    lanes: Layer  # lanes_polygons
    lane_connectors: Layer  # lane_connectors (attributes only; polygons below)
    connector_polygons: Layer  # gen_lane_connectors_scaled_width_polygons, ids = lane connector ids
    roadblocks: Layer  # lane_groups_polygons
    roadblock_connectors: Layer  # lane_group_connectors
    intersections: Layer
    carpark_areas: Layer
    drivable_areas: Layer  # generic_drivable_areas
    crosswalks: Layer
    walkways: Layer
    baselines: dict[str, FloatArray]  # lane or lane-connector id -> (n, 2) vertices

    @cached_property
    def lane_outgoing(self) -> dict[str, list[str]]:
        """Return lane id -> lane connectors leaving it (`exit_lane_fid`), in table order."""
        return _group(self.lane_connectors, "exit_lane_fid")

    @cached_property
    def lane_incoming(self) -> dict[str, list[str]]:
        """Return lane id -> lane connectors entering it (`entry_lane_fid`), in table order."""
        return _group(self.lane_connectors, "entry_lane_fid")

    @cached_property
    def roadblock_lanes(self) -> dict[str, list[str]]:
        """Return roadblock id -> its lanes (`lane_group_fid`), in table order."""
        return _group(self.lanes, "lane_group_fid")

    @cached_property
    def roadblock_connector_lanes(self) -> dict[str, list[str]]:
        """Return roadblock-connector id -> its lane connectors (`lane_group_connector_fid`), in table order."""
        return _group(self.lane_connectors, "lane_group_connector_fid")

    @cached_property
    def roadblock_outgoing(self) -> dict[str, list[str]]:
        """Return roadblock id -> roadblock connectors leaving it (`from_lane_group_fid`), in table order."""
        return _group(self.roadblock_connectors, "from_lane_group_fid")

    @cached_property
    def roadblock_incoming(self) -> dict[str, list[str]]:
        """Return roadblock id -> roadblock connectors entering it (`to_lane_group_fid`), in table order."""
        return _group(self.roadblock_connectors, "to_lane_group_fid")


def _group(layer: Layer, column: str) -> dict[str, list[str]]:
    groups: dict[str, list[str]] = defaultdict(list)
    for object_id, parent in zip(layer.ids, layer.attributes[column], strict=True):
        if parent is not None:
            groups[parent].append(object_id)
    return dict(groups)


def load_map_tables(path: Path | str, location: str) -> MapTables:
    """Return every layer the excerpt needs from a GeoPackage, reprojected to its `meta` projected system."""
    path = Path(path)
    try:
        connection = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.Error as error:
        raise MapFormatError(f"{path}: cannot open ({error})") from None
    try:
        reader = _GeoPackage(connection, path)
        baseline_layer = reader.layer("baseline_paths", {"lane_fid": _id, "lane_connector_fid": _id})
        speed = {"speed_limit_mps": _speed_limit}
        return MapTables(
            location=location,
            path=path,
            lanes=reader.layer("lanes_polygons", {"lane_group_fid": _id, **speed}),
            lane_connectors=reader.layer(
                "lane_connectors",
                {"exit_lane_fid": _id, "entry_lane_fid": _id, "lane_group_connector_fid": _id, **speed},
            ),
            connector_polygons=_keyed_by(
                reader.layer("gen_lane_connectors_scaled_width_polygons", {"lane_connector_fid": _id}),
                "lane_connector_fid",
            ),
            roadblocks=reader.layer("lane_groups_polygons", {}),
            roadblock_connectors=reader.layer(
                "lane_group_connectors", {"from_lane_group_fid": _id, "to_lane_group_fid": _id}
            ),
            intersections=reader.layer("intersections", {}),
            carpark_areas=reader.layer("carpark_areas", {}),
            drivable_areas=reader.layer("generic_drivable_areas", {}),
            crosswalks=reader.layer("crosswalks", {}),
            walkways=reader.layer("walkways", {}),
            baselines=_baselines(baseline_layer),
        )
    except sqlite3.Error as error:
        raise MapFormatError(f"{path}: {error}") from None
    finally:
        connection.close()


def _keyed_by(layer: Layer, column: str) -> Layer:
    """Re-key a layer by a foreign-key column, keeping the first row per key (devkit: first match wins)."""
    first_rows: dict[str, int] = {}
    for row, key in enumerate(layer.attributes[column]):
        if key is not None:
            first_rows.setdefault(key, row)
    rows = np.fromiter(first_rows.values(), dtype=np.int64, count=len(first_rows))
    return Layer(layer.table, tuple(first_rows), layer.geometries[rows], {})


def _baselines(layer: Layer) -> dict[str, FloatArray]:
    baselines: dict[str, FloatArray] = {}
    for row in range(len(layer.ids)):
        geometry = layer.geometries[row]
        owner = layer.attributes["lane_fid"][row] or layer.attributes["lane_connector_fid"][row]
        if owner is None or owner in baselines:
            continue
        if isinstance(geometry, shapely.MultiLineString) and len(geometry.geoms) == 1:
            geometry = geometry.geoms[0]
        if not isinstance(geometry, shapely.LineString):
            raise MapFormatError(
                f"baseline_paths fid {layer.ids[row]}: expected a line, got {geometry.geom_type}"
            )
        baselines[owner] = shapely.get_coordinates(geometry)
    return baselines


class _GeoPackage:
    """Table access with the projection of the `meta` table."""

    def __init__(self, connection: sqlite3.Connection, path: Path) -> None:
        self.connection = connection
        self.path = path
        rows = connection.execute("SELECT value FROM meta WHERE key = 'projectedCoordSystem'").fetchall()
        if len(rows) != 1:
            raise MapFormatError(f"{path}: meta: expected one projectedCoordSystem entry, found {len(rows)}")
        try:
            self.projected = pyproj.CRS.from_user_input(rows[0][0])
        except pyproj.exceptions.CRSError as error:
            raise MapFormatError(
                f"{path}: meta: projectedCoordSystem {rows[0][0]!r} is not a CRS ({error})"
            ) from None

    def layer(self, table: str, columns: dict[str, Any]) -> Layer:
        geometry_column, srs_id = self._geometry_column(table)
        key = self._primary_key(table)
        selected = ", ".join(_quote(name) for name in (key, geometry_column, *columns))
        try:
            rows = self.connection.execute(
                f"SELECT {selected} FROM {_quote(table)} ORDER BY {_quote(key)}"
            ).fetchall()
        except sqlite3.OperationalError as error:
            raise MapFormatError(f"{self.path}: table {table}: {error}") from None
        ids = tuple(str(row[0]) for row in rows)
        wkb = [_wkb(row[1], f"{self.path}: {table} fid {row[0]}") for row in rows]
        geometries = shapely.from_wkb(np.array(wkb, dtype=object)) if rows else np.empty(0, dtype=object)
        attributes = {
            name: tuple(parse(row[index + 2]) for row in rows)
            for index, (name, parse) in enumerate(columns.items())
        }
        return Layer(table, ids, self._project(geometries, srs_id, table), attributes)

    def _geometry_column(self, table: str) -> tuple[str, int]:
        rows = self.connection.execute(
            "SELECT column_name, srs_id FROM gpkg_geometry_columns WHERE table_name = ?", (table,)
        ).fetchall()
        if len(rows) != 1:
            raise MapFormatError(
                f"{self.path}: table {table}: not a GeoPackage feature table (gpkg_geometry_columns)"
            )
        return rows[0][0], rows[0][1]

    def _primary_key(self, table: str) -> str:
        keys = [
            row[1] for row in self.connection.execute(f"PRAGMA table_info({_quote(table)})") if row[5] == 1
        ]
        if len(keys) != 1:
            raise MapFormatError(
                f"{self.path}: table {table}: expected one integer primary key (the feature id)"
            )
        return keys[0]

    def _project(self, geometries: np.ndarray, srs_id: int, table: str) -> np.ndarray:
        source = self._crs(srs_id, table)
        if source.is_exact_same(self.projected):
            return geometries
        transformer = pyproj.Transformer.from_crs(source, self.projected, always_xy=True)

        def project(xy: FloatArray) -> FloatArray:
            x, y = transformer.transform(xy[:, 0], xy[:, 1], errcheck=True)
            return np.column_stack([x, y])

        return shapely.transform(geometries, project)

    def _crs(self, srs_id: int, table: str) -> pyproj.CRS:
        rows = self.connection.execute(
            "SELECT organization, organization_coordsys_id, definition FROM gpkg_spatial_ref_sys WHERE srs_id = ?",
            (srs_id,),
        ).fetchall()
        if len(rows) != 1 or srs_id <= 0:
            raise MapFormatError(
                f"{self.path}: table {table}: srs_id {srs_id} has no usable CRS in gpkg_spatial_ref_sys"
            )
        organization, code, definition = rows[0]
        try:
            if str(organization).upper() == "EPSG":
                return pyproj.CRS.from_epsg(code)
            return pyproj.CRS.from_wkt(definition)
        except pyproj.exceptions.CRSError as error:
            raise MapFormatError(f"{self.path}: table {table}: srs_id {srs_id}: {error}") from None


def _wkb(blob: bytes | None, where: str) -> bytes:
    """Return the WKB body of a GeoPackage geometry blob (header: GP, version, flags, srs_id, envelope)."""
    if blob is None or len(blob) < 8 or blob[:2] != b"GP":
        raise MapFormatError(f"{where}: not a GeoPackage geometry blob")
    flags = blob[3]
    if flags & 0b0010_0000:
        raise MapFormatError(f"{where}: extended GeoPackage geometries are not supported")
    envelope = _ENVELOPE_BYTES.get((flags >> 1) & 0b111)
    if envelope is None:
        raise MapFormatError(f"{where}: invalid envelope indicator in the geometry header")
    return bytes(blob[8 + envelope :])


def _id(value: Any) -> str | None:
    """Return a nuPlan foreign key as the decimal string the devkit compares (nullable integers read as float)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return str(int(value))


def _speed_limit(value: Any) -> float | None:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return float(value)


def _quote(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def layer_rows(layer: Layer, ids: Collection[str]) -> list[int]:
    """Return the rows of the given ids that exist in `layer`, in table order."""
    return sorted(layer.row_of[object_id] for object_id in ids if object_id in layer.row_of)
