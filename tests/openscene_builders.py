"""Small fixtures in the upstream formats for the OpenScene importer tests.

A nuPlan-style GeoPackage (WGS84 storage, UTM 11N in `meta`) with a straight eastbound road of
60 roadblocks (2 lanes each) joined by roadblock connectors, a left-turn branch at roadblock 22,
an isolated and a far roadblock, and area layers; plus OpenScene log pickles (protocol 5) of an
ego driving along that road among agents and static objects, built from ground truth by the
OpenScene generator's forward transforms.
"""

from __future__ import annotations

import itertools
import math
import pickle
import sqlite3
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyproj
import shapely

from scorer.openscene.frames import quaternion_yaw

X0, Y0 = 664000.0, 3997000.0  # Las Vegas, UTM zone 11N
PROJECTED_CRS = "epsg:32611"
LOCATION = "us-nv-las-vegas-strip"
MAP_VERSION = "9.15.1915"
BLOCKS = 60
BLOCK_LENGTH, BLOCK_PITCH, LANE_WIDTH = 40.0, 50.0, 3.5
LEFT_TURN_BLOCK = 22


def intersection_id(i: int) -> int:  # the straight stretch of roadblock connector i
    return 7010 + i


def roadblock_id(i: int) -> int:
    return 1000 + i


def connector_id(i: int) -> int:
    return 2000 + i


def lane_id(i: int, side: int) -> int:  # side 0 = left lane (lane_index 0), 1 = right
    return 3000 + 2 * i + side


def lane_connector_id(i: int, side: int) -> int:
    return 4000 + 2 * i + side


ISOLATED_BLOCK, FAR_BLOCK = 1500, 1501
TURN_CONNECTOR, TURN_LANE_CONNECTOR = 2500, 4500
NORTH_BLOCKS = (1600, 1601)
NORTH_LANES = (3600, 3601)
NORTH_CONNECTOR, NORTH_LANE_CONNECTOR = 2600, 4600
RIGHT_TURN_BLOCK = 30
RIGHT_CONNECTOR, RIGHT_LANE_CONNECTOR, SOUTH_BLOCK, SOUTH_LANE = 2501, 4501, 1700, 3700
INTERSECTION, CARPARK, DRIVABLE, CROSSWALK, WALKWAY, FAR_WALKWAY = 7000, 7100, 7200, 7300, 7400, 7401


def box(x0: float, y0: float, x1: float, y1: float) -> shapely.Polygon:
    return shapely.box(X0 + x0, Y0 + y0, X0 + x1, Y0 + y1)


def line(*points: tuple[float, float]) -> shapely.LineString:
    return shapely.LineString([(X0 + x, Y0 + y) for x, y in points])


@dataclass
class Table:
    """A feature table: rows of (fid, geometry, {column: value})."""

    name: str
    columns: dict[str, str]
    rows: list[tuple[int, shapely.Geometry, dict[str, Any]]] = field(default_factory=list)


def road_map() -> dict[str, Table]:
    """Return the map's feature tables in the projected frame (UTM metres)."""
    speed = {"speed_limit_mps": "REAL"}
    tables = {
        name: Table(name, columns)
        for name, columns in {
            "lanes_polygons": {
                "lane_fid": "INTEGER",
                "lane_group_fid": "INTEGER",
                "lane_index": "INTEGER",
                **speed,
            },
            "lane_connectors": {
                "exit_lane_fid": "INTEGER",
                "entry_lane_fid": "INTEGER",
                "lane_group_connector_fid": "INTEGER",
                "traffic_light_stop_line_fids": "TEXT",
                **speed,
            },
            "gen_lane_connectors_scaled_width_polygons": {"lane_connector_fid": "INTEGER"},
            "baseline_paths": {"lane_fid": "INTEGER", "lane_connector_fid": "INTEGER"},
            "lane_groups_polygons": {},
            "lane_group_connectors": {"from_lane_group_fid": "INTEGER", "to_lane_group_fid": "INTEGER"},
            "intersections": {},
            "carpark_areas": {},
            "generic_drivable_areas": {},
            "crosswalks": {},
            "walkways": {},
            "boundaries": {},
        }.items()
    }
    baseline_fid = iter(range(5000, 6000))
    polygon_fid = iter(range(6000, 7000))

    def add_lane(
        fid: int, block: int, index: int, polygon: shapely.Polygon, baseline: shapely.LineString, limit
    ) -> None:
        tables["lanes_polygons"].rows.append(
            (
                fid,
                polygon,
                {"lane_fid": fid, "lane_group_fid": block, "lane_index": index, "speed_limit_mps": limit},
            )
        )
        tables["baseline_paths"].rows.append(
            (next(baseline_fid), baseline, {"lane_fid": fid, "lane_connector_fid": None})
        )

    def add_lane_connector(
        fid: int, block: int, exit_lane: int, entry_lane: int, baseline: shapely.LineString
    ) -> None:
        tables["lane_connectors"].rows.append(
            (
                fid,
                baseline,
                {
                    "exit_lane_fid": exit_lane,
                    "entry_lane_fid": entry_lane,
                    "lane_group_connector_fid": block,
                    "traffic_light_stop_line_fids": "",
                    "speed_limit_mps": 15.0,
                },
            )
        )
        tables["gen_lane_connectors_scaled_width_polygons"].rows.append(
            (
                next(polygon_fid),
                baseline.buffer(LANE_WIDTH / 2, cap_style="flat"),
                {"lane_connector_fid": fid},
            )
        )
        tables["baseline_paths"].rows.append(
            (next(baseline_fid), baseline, {"lane_fid": None, "lane_connector_fid": fid})
        )

    for i in range(BLOCKS):
        start, end = i * BLOCK_PITCH, i * BLOCK_PITCH + BLOCK_LENGTH
        tables["lane_groups_polygons"].rows.append((roadblock_id(i), box(start, 0, end, 2 * LANE_WIDTH), {}))
        for side in (0, 1):
            y = (1.5 - side) * LANE_WIDTH
            limit = None if i == 21 and side == 1 else 13.4
            add_lane(
                lane_id(i, side),
                roadblock_id(i),
                side,
                box(start, y - LANE_WIDTH / 2, end, y + LANE_WIDTH / 2),
                line(*((start + k * BLOCK_LENGTH / 4, y) for k in range(5))),
                limit,
            )
        if i + 1 < BLOCKS:
            tables["lane_group_connectors"].rows.append(
                (
                    connector_id(i),
                    box(end, 0, end + BLOCK_PITCH - BLOCK_LENGTH, 2 * LANE_WIDTH),
                    {"from_lane_group_fid": roadblock_id(i), "to_lane_group_fid": roadblock_id(i + 1)},
                )
            )
            for side in (0, 1):
                y = (1.5 - side) * LANE_WIDTH
                add_lane_connector(
                    lane_connector_id(i, side),
                    connector_id(i),
                    lane_id(i, side),
                    lane_id(i + 1, side),
                    line((end, y), (end + 5, y), (end + BLOCK_PITCH - BLOCK_LENGTH, y)),
                )
    # Left turn from roadblock 22 onto a northbound road.
    turn_x = LEFT_TURN_BLOCK * BLOCK_PITCH + BLOCK_LENGTH
    tables["lane_group_connectors"].rows.append(
        (
            TURN_CONNECTOR,
            box(turn_x, 0, turn_x + 10, 12),
            {"from_lane_group_fid": roadblock_id(LEFT_TURN_BLOCK), "to_lane_group_fid": NORTH_BLOCKS[0]},
        )
    )
    add_lane_connector(
        TURN_LANE_CONNECTOR,
        TURN_CONNECTOR,
        lane_id(LEFT_TURN_BLOCK, 0),
        NORTH_LANES[0],
        line((turn_x, 5.25), (turn_x + 3, 5.6), (turn_x + 5.5, 7.5), (turn_x + 6.5, 12)),
    )
    for k, (block, lane) in enumerate(zip(NORTH_BLOCKS, NORTH_LANES, strict=True)):
        y0, y1 = 12 + k * BLOCK_PITCH, 12 + k * BLOCK_PITCH + BLOCK_LENGTH
        tables["lane_groups_polygons"].rows.append((block, box(turn_x + 4.75, y0, turn_x + 8.25, y1), {}))
        add_lane(
            lane,
            block,
            0,
            box(turn_x + 4.75, y0, turn_x + 8.25, y1),
            line((turn_x + 6.5, y0), (turn_x + 6.5, y1)),
            10.0,
        )
    tables["lane_group_connectors"].rows.append(
        (
            NORTH_CONNECTOR,
            box(turn_x + 4.75, 52, turn_x + 8.25, 62),
            {"from_lane_group_fid": NORTH_BLOCKS[0], "to_lane_group_fid": NORTH_BLOCKS[1]},
        )
    )
    add_lane_connector(
        NORTH_LANE_CONNECTOR,
        NORTH_CONNECTOR,
        NORTH_LANES[0],
        NORTH_LANES[1],
        line((turn_x + 6.5, 52), (turn_x + 6.5, 62)),
    )
    # Right turn from roadblock 30 onto a southbound road.
    right_x = RIGHT_TURN_BLOCK * BLOCK_PITCH + BLOCK_LENGTH
    tables["lane_group_connectors"].rows.append(
        (
            RIGHT_CONNECTOR,
            box(right_x, -5, right_x + 10, 7),
            {"from_lane_group_fid": roadblock_id(RIGHT_TURN_BLOCK), "to_lane_group_fid": SOUTH_BLOCK},
        )
    )
    add_lane_connector(
        RIGHT_LANE_CONNECTOR,
        RIGHT_CONNECTOR,
        lane_id(RIGHT_TURN_BLOCK, 1),
        SOUTH_LANE,
        line((right_x, 1.75), (right_x + 3, 1.4), (right_x + 5.5, -0.5), (right_x + 6.5, -5)),
    )
    tables["lane_groups_polygons"].rows.append(
        (SOUTH_BLOCK, box(right_x + 4.75, -45, right_x + 8.25, -5), {})
    )
    add_lane(
        SOUTH_LANE,
        SOUTH_BLOCK,
        0,
        box(right_x + 4.75, -45, right_x + 8.25, -5),
        line((right_x + 6.5, -5), (right_x + 6.5, -45)),
        10.0,
    )
    # An unconnected roadblock beside the road (no lanes), and one far away.
    tables["lane_groups_polygons"].rows.append((ISOLATED_BLOCK, box(1000, 20, 1040, 27), {}))
    tables["lane_groups_polygons"].rows.append((FAR_BLOCK, box(-5000, 5000, -4960, 5007), {}))
    # Area layers: the junction (with a hole), a car park, a generic drivable area, crosswalk and walkways.
    junction = shapely.Polygon(
        shapely.get_coordinates(box(turn_x - 2, -2, turn_x + 12, 14).exterior),
        holes=[shapely.get_coordinates(box(turn_x + 9, 9, turn_x + 10, 10).exterior)],
    )
    tables["intersections"].rows.append((INTERSECTION, junction, {}))
    # As in nuPlan, the stretches between roadblocks lie in intersections (connector polygons are not drivable).
    for i in range(BLOCKS - 1):
        end = i * BLOCK_PITCH + BLOCK_LENGTH
        tables["intersections"].rows.append((intersection_id(i), box(end - 0.5, -0.5, end + 10.5, 7.5), {}))
    tables["carpark_areas"].rows.append((CARPARK, box(1000, -40, 1030, -10), {}))
    tables["generic_drivable_areas"].rows.append((DRIVABLE, box(1030, -10, 1040, 0), {}))
    tables["crosswalks"].rows.append((CROSSWALK, box(1045, 0, 1048, 7), {}))
    tables["walkways"].rows.append((WALKWAY, box(900, -3, 1200, 0), {}))
    tables["walkways"].rows.append((FAR_WALKWAY, box(3000, -3, 3100, 0), {}))
    tables["boundaries"].rows.append((9000, line((0, 0), (10, 0)), {}))
    return tables


def gpkg_blob(geometry: shapely.Geometry, srs_id: int, envelope: bool = True) -> bytes:
    """Return a GeoPackage geometry blob: GP header (little endian, optional xy envelope) + WKB."""
    flags = 0b0000_0001 | (0b0000_0010 if envelope else 0)
    header = b"GP" + bytes([0, flags]) + struct.pack("<i", srs_id)
    if envelope:
        minx, miny, maxx, maxy = geometry.bounds
        header += struct.pack("<4d", minx, maxx, miny, maxy)
    return header + shapely.to_wkb(geometry, byte_order=1, flavor="iso")


def write_gpkg(
    path: Path,
    tables: dict[str, Table],
    storage_epsg: int = 4326,
    projected: str = PROJECTED_CRS,
    reverse_rows: bool = False,
) -> None:
    """Write the tables as a GeoPackage storing geometries in `storage_epsg` (reprojected from UTM)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    to_storage = pyproj.Transformer.from_crs(PROJECTED_CRS, f"epsg:{storage_epsg}", always_xy=True)
    connection = sqlite3.connect(path)
    connection.executescript(
        """
        CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT, srs_id INTEGER PRIMARY KEY, organization TEXT,
            organization_coordsys_id INTEGER, definition TEXT, description TEXT);
        CREATE TABLE gpkg_contents (table_name TEXT PRIMARY KEY, data_type TEXT, identifier TEXT, srs_id INTEGER);
        CREATE TABLE gpkg_geometry_columns (table_name TEXT, column_name TEXT, geometry_type_name TEXT,
            srs_id INTEGER, z INTEGER, m INTEGER);
        CREATE TABLE meta (fid INTEGER PRIMARY KEY, key TEXT, value TEXT);
        """
    )
    connection.execute(
        "INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, 'EPSG', ?, ?, '')",
        (f"EPSG:{storage_epsg}", storage_epsg, storage_epsg, pyproj.CRS.from_epsg(storage_epsg).to_wkt()),
    )
    connection.executemany(
        "INSERT INTO meta (key, value) VALUES (?, ?)",
        [("geographicCoordSystem", "epsg:4326"), ("projectedCoordSystem", projected)],
    )
    for table in tables.values():
        columns = "".join(f', "{name}" {kind}' for name, kind in table.columns.items())
        connection.execute(
            f'CREATE TABLE "{table.name}" (fid INTEGER PRIMARY KEY AUTOINCREMENT, geom BLOB{columns})'
        )
        connection.execute(
            "INSERT INTO gpkg_contents VALUES (?, 'features', ?, ?)", (table.name, table.name, storage_epsg)
        )
        connection.execute(
            "INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', 'GEOMETRY', ?, 0, 0)",
            (table.name, storage_epsg),
        )
        rows = list(reversed(table.rows)) if reverse_rows else table.rows
        for index, (fid, geometry, values) in enumerate(rows):
            stored = shapely.transform(
                geometry, lambda xy: np.column_stack(to_storage.transform(xy[:, 0], xy[:, 1]))
            )
            names = ", ".join(f'"{name}"' for name in ("fid", "geom", *values))
            marks = ", ".join("?" for _ in range(2 + len(values)))
            connection.execute(
                f'INSERT INTO "{table.name}" ({names}) VALUES ({marks})',
                (fid, gpkg_blob(stored, storage_epsg, envelope=index % 2 == 0), *values.values()),
            )
    connection.commit()
    connection.close()


def write_maps(maps_dir: Path, storage_epsg: int = 4326) -> Path:
    """Write the map root: nuplan-maps-v1.0.json and <location>/<version>/map.gpkg; return the gpkg path."""
    path = maps_dir / LOCATION / MAP_VERSION / "map.gpkg"
    write_gpkg(path, road_map(), storage_epsg)
    (maps_dir / "nuplan-maps-v1.0.json").write_text(
        f'{{"{LOCATION}": {{"version": "{MAP_VERSION}", "layers": {{}}}}}}'
    )
    return path


# --- logs ----------------------------------------------------------------------------------------


def quaternion(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Return [w, x, y, z] of the z-y'-x'' rotation (yaw, pitch, roll)."""
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


@dataclass(frozen=True)
class TruthObject:
    """Ground truth of one annotated object in one frame (global frame)."""

    track: str
    name: str
    x: float
    y: float
    heading: float
    velocity: tuple[float, float]
    size: tuple[float, float, float] = (4.5, 2.0, 1.6)


@dataclass
class TruthFrame:
    token: str
    timestamp: int
    x: float
    y: float
    yaw: float
    objects: list[TruthObject]
    route: list[str]
    command: list[int] | None
    dynamics: tuple[float, float, float, float] = (10.0, 0.1, 0.5, -0.05)
    lights: list[tuple[int, bool]] = field(default_factory=list)
    roll_pitch: tuple[float, float] = (0.0, 0.0)


def frame_token(log_index: int, k: int) -> str:
    return f"{log_index:04x}{k:012x}"


def road_frames(
    log_index: int = 1,
    count: int = 40,
    start_x: float = 960.0,
    with_commands: bool = True,
    yaw_amplitude: float = 0.1,
) -> list[TruthFrame]:
    """Return ground truth of an ego driving east at 10 m/s in the right lane among other objects."""
    route = [str(i) for b in range(19, 26) for i in (roadblock_id(b), connector_id(b))]
    frames = []
    for k in range(count):
        ego_x = X0 + start_x + 5.0 * k
        yaw = yaw_amplitude * math.sin(0.7 * k)  # crosses zero, so box headings near pi wrap sometimes
        objects = [
            TruthObject("lead", "vehicle", ego_x + 20.0, Y0 + 1.75, 0.02, (8.0, 0.16)),
            TruthObject(
                "walker",
                "pedestrian",
                X0 + 1000.0,
                Y0 + 9.0 + 0.5 * k,
                math.pi / 2,
                (0.0, 1.0),
                (0.5, 0.5, 1.8),
            ),
            TruthObject("oncoming", "bicycle", ego_x + 30.0, Y0 + 5.25, 3.13, (-5.0, 0.0), (1.8, 0.6, 1.5)),
            TruthObject("cone", "traffic_cone", X0 + 1100.0, Y0 + 7.6, 0.3, (0.4, -0.2), (0.3, 0.3, 0.7)),
        ]
        if k % 3 == 0:
            objects += [
                TruthObject("barrier", "barrier", X0 + 1080.0, Y0 - 1.0, 0.0, (0.0, 0.0), (2.0, 0.4, 1.0)),
                TruthObject("sign", "czone_sign", X0 + 1090.0, Y0 - 1.5, 1.0, (0.0, 0.0), (0.5, 0.2, 1.2)),
                TruthObject(
                    "thing", "generic_object", X0 + 1095.0, Y0 - 2.0, -2.0, (0.0, 0.0), (1.0, 1.0, 1.0)
                ),
            ]
        if 10 <= k < 16:
            objects.append(TruthObject("brief", "vehicle", ego_x - 15.0, Y0 + 5.25, -3.0, (-1.0, 0.5)))
        frames.append(
            TruthFrame(
                token=frame_token(log_index, k),
                timestamp=1_620_000_000_000_000 + 500_000 * k + (k % 4) * 137,
                x=ego_x,
                y=Y0 + 1.75 + 0.01 * k,
                yaw=yaw,
                objects=objects,
                route=[] if k == 25 else route,
                command=([0, 1, 0, 0] if with_commands else None),
                lights=[(lane_connector_id(20, 0), k % 2 == 0), (lane_connector_id(21, 1), False)],
                roll_pitch=(0.02, -0.01) if k in (7, 8) else (0.0, 0.0),
            )
        )
    return frames


def log_frame(
    truth: TruthFrame, log_name: str, location: str = LOCATION, test_mode: bool = False
) -> dict[str, Any]:
    """Return the OpenScene frame dict of ground truth, with the generator's forward transforms."""
    roll, pitch = truth.roll_pitch
    rotation = quaternion(truth.yaw, pitch, roll)
    translation = np.array([truth.x, truth.y, 600.0])
    w, x, y, z = rotation
    matrix = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    inverse = np.linalg.inv(matrix)
    frame: dict[str, Any] = {
        "token": truth.token,
        "frame_idx": 0,
        "timestamp": truth.timestamp,
        "log_name": log_name,
        "log_token": "feedfacefeedface",
        "scene_name": "log-0001-scene",
        "scene_token": "5ce5ce5ce5ce5ce5",
        "map_location": location,
        "roadblock_ids": list(truth.route),
        "vehicle_name": "veh-35",
        "can_bus": np.concatenate([translation, rotation, np.zeros(11)]),
        "lidar_path": f"{log_name}/MergedPointCloud/{truth.token}.pcd",
        "lidar2ego_translation": np.array([1.5, 0.0, 1.8]),
        "lidar2ego_rotation": [1.0, 0.0, 0.0, 0.0],
        "ego2global_translation": translation,
        "ego2global_rotation": rotation,
        "ego_dynamic_state": list(truth.dynamics),
        "traffic_lights": list(truth.lights),
        "cams": {
            name: {
                "data_path": f"{log_name}/{name}/{truth.token}.jpg",
                "sensor2lidar_rotation": np.eye(3),
                "sensor2lidar_translation": np.zeros(3),
                "cam_intrinsic": np.eye(3),
                "distortion": np.zeros(5),
            }
            for name in ("CAM_F0", "CAM_L0", "CAM_L1", "CAM_L2", "CAM_R0", "CAM_R1", "CAM_R2", "CAM_B0")
        },
        "sample_prev": None,
        "sample_next": None,
    }
    if truth.command is not None:
        frame["driving_command"] = np.array(truth.command)
    if not test_mode:
        objects = truth.objects
        offsets = np.array([[o.x - truth.x, o.y - truth.y, 0.8] for o in objects]).reshape(-1, 3)
        locations = (inverse @ offsets.T).T
        velocities = (inverse @ np.array([[*o.velocity, 0.0] for o in objects]).reshape(-1, 3).T).T
        frame["anns"] = {
            "gt_boxes": np.concatenate(
                [
                    locations,
                    np.array([o.size for o in objects]).reshape(-1, 3),
                    np.array([[o.heading - truth.yaw] for o in objects]).reshape(-1, 1),
                ],
                axis=1,
            ),
            "gt_names": np.array([o.name for o in objects]),
            "gt_velocity_3d": velocities.reshape(-1, 3),
            "instance_tokens": [f"{truth.token[:8]}{index:08x}" for index in range(len(objects))],
            "track_tokens": [o.track for o in objects],
        }
    return frame


def write_log(path: Path, frames: list[dict[str, Any]]) -> None:
    """Write frame dicts as the OpenScene generator does (pickle.HIGHEST_PROTOCOL, here 5)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(frames, protocol=5))


LOG_NAME = "2021.05.12.22.00.38_veh-35_01008_01518"


def write_road_log(logs_dir: Path, log_index: int = 1, **kwargs: Any) -> tuple[Path, list[TruthFrame]]:
    """Write the road log; return its path and the ground truth."""
    truth = road_frames(log_index, **kwargs)
    name = f"{LOG_NAME[:-5]}{log_index:05d}"
    path = logs_dir / f"{name}.pkl"
    write_log(path, [log_frame(frame, name) for frame in truth])
    return path, truth


# --- scene files back to upstream formats ------------------------------------------------------------


def exact_yaw_quaternion(heading: float) -> list[float]:
    """Return a unit quaternion [w, 0, 0, z] whose pyquaternion yaw is exactly `heading` (nearest ulps first)."""
    w, z = math.cos(heading / 2), math.sin(heading / 2)
    for radius in range(40):
        for dw, dz in itertools.product(range(-radius, radius + 1), repeat=2):
            candidate = [w + dw * float(np.spacing(w)), 0.0, 0.0, z + dz * float(np.spacing(z))]
            if max(abs(dw), abs(dz)) == radius and quaternion_yaw(candidate) == heading:
                return candidate
    raise AssertionError(f"no quaternion reproduces heading {heading!r}")


def map_tables(raw_map: dict[str, list[dict[str, Any]]]) -> dict[str, Table]:
    """Return the GeoPackage tables of a scene's map excerpt (ids unchanged, rows in file order)."""
    speed = {"speed_limit_mps": "REAL"}
    tables = {
        "lanes_polygons": Table(
            "lanes_polygons", {"lane_fid": "INTEGER", "lane_group_fid": "INTEGER", **speed}
        ),
        "lane_connectors": Table(
            "lane_connectors",
            {
                "exit_lane_fid": "INTEGER",
                "entry_lane_fid": "INTEGER",
                "lane_group_connector_fid": "INTEGER",
                **speed,
            },
        ),
        "gen_lane_connectors_scaled_width_polygons": Table(
            "gen_lane_connectors_scaled_width_polygons", {"lane_connector_fid": "INTEGER"}
        ),
        "baseline_paths": Table("baseline_paths", {"lane_fid": "INTEGER", "lane_connector_fid": "INTEGER"}),
        "lane_groups_polygons": Table("lane_groups_polygons", {}),
        "lane_group_connectors": Table(
            "lane_group_connectors", {"from_lane_group_fid": "INTEGER", "to_lane_group_fid": "INTEGER"}
        ),
        **{
            name: Table(name, {})
            for name in ("intersections", "carpark_areas", "generic_drivable_areas", "crosswalks", "walkways")
        },
    }
    extra_fid = itertools.count(1)
    for lane in raw_map["lanes"]:
        tables["lanes_polygons"].rows.append(
            (
                int(lane["id"]),
                shapely.Polygon(lane["polygon"]),
                {
                    "lane_fid": int(lane["id"]),
                    "lane_group_fid": int(lane["roadblock"]),
                    "speed_limit_mps": lane["speed_limit_mps"],
                },
            )
        )
        tables["baseline_paths"].rows.append(
            (
                next(extra_fid),
                shapely.LineString(lane["baseline"]),
                {"lane_fid": int(lane["id"]), "lane_connector_fid": None},
            )
        )
    for connector in raw_map["lane_connectors"]:
        tables["lane_connectors"].rows.append(
            (
                int(connector["id"]),
                shapely.LineString(connector["baseline"]),
                {
                    "exit_lane_fid": int(connector["incoming"][0]),
                    "entry_lane_fid": int(connector["outgoing"][0]),
                    "lane_group_connector_fid": int(connector["roadblock"]),
                    "speed_limit_mps": connector["speed_limit_mps"],
                },
            )
        )
        tables["gen_lane_connectors_scaled_width_polygons"].rows.append(
            (
                next(extra_fid),
                shapely.Polygon(connector["polygon"]),
                {"lane_connector_fid": int(connector["id"])},
            )
        )
        tables["baseline_paths"].rows.append(
            (
                next(extra_fid),
                shapely.LineString(connector["baseline"]),
                {"lane_fid": None, "lane_connector_fid": int(connector["id"])},
            )
        )
    for block in raw_map["roadblocks"]:
        tables["lane_groups_polygons"].rows.append((int(block["id"]), shapely.Polygon(block["polygon"]), {}))
    for block in raw_map["roadblock_connectors"]:
        tables["lane_group_connectors"].rows.append(
            (
                int(block["id"]),
                shapely.Polygon(block["polygon"]),
                {
                    "from_lane_group_fid": int(block["incoming"][0]),
                    "to_lane_group_fid": int(block["outgoing"][0]),
                },
            )
        )
    for layer, table in (
        ("intersections", "intersections"),
        ("carpark_areas", "carpark_areas"),
        ("drivable_areas", "generic_drivable_areas"),
        ("crosswalks", "crosswalks"),
        ("walkways", "walkways"),
    ):
        for area in raw_map.get(layer, []):
            tables[table].rows.append((int(area["id"]), shapely.Polygon(area["polygon"]), {}))
    return tables
