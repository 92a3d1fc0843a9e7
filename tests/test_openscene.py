"""OpenScene log pickles, frame conversion, GeoPackage reading and map excerpts."""

from __future__ import annotations

import math
import os
import pickle
import struct
from pathlib import Path

import numpy as np
import pytest
import shapely
from openscene_builders import (
    CARPARK,
    CROSSWALK,
    DRIVABLE,
    FAR_BLOCK,
    FAR_WALKWAY,
    INTERSECTION,
    ISOLATED_BLOCK,
    LOCATION,
    NORTH_BLOCKS,
    NORTH_CONNECTOR,
    RIGHT_CONNECTOR,
    SOUTH_BLOCK,
    TURN_CONNECTOR,
    WALKWAY,
    X0,
    Y0,
    connector_id,
    intersection_id,
    lane_connector_id,
    lane_id,
    log_frame,
    road_frames,
    road_map,
    roadblock_id,
    write_gpkg,
    write_maps,
    write_road_log,
)

from scorer.geometry import ego_center, rear_axle_round_trip
from scorer.openscene.excerpt import build_excerpt, excerpt_to_json
from scorer.openscene.frames import (
    EgoPose,
    FrameError,
    convert_frame,
    ego_pose,
    quaternion_yaw,
    scene_windows,
    window_problem,
)
from scorer.openscene.gpkg import MapFormatError, gpkg_path, load_map_tables, map_location
from scorer.openscene.log_pickle import LogFormatError, load_log
from scorer.scene import parse_scene


@pytest.fixture(scope="module")
def maps_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    maps = tmp_path_factory.mktemp("maps")
    write_maps(maps)
    return maps


@pytest.fixture(scope="module")
def tables(maps_dir: Path):
    return load_map_tables(gpkg_path(maps_dir, LOCATION), LOCATION)


# --- log pickles ---------------------------------------------------------------------------------


def test_log_pickle_round_trip_keeps_arrays_and_order(tmp_path: Path) -> None:
    path, truth = write_road_log(tmp_path)
    frames = load_log(path)
    assert [frame["token"] for frame in frames] == [t.token for t in truth]
    original = pickle.loads(path.read_bytes())
    assert frames[5]["anns"]["gt_names"].dtype.kind == "U"
    np.testing.assert_array_equal(frames[5]["anns"]["gt_boxes"], original[5]["anns"]["gt_boxes"])
    np.testing.assert_array_equal(frames[5]["ego2global_rotation"], original[5]["ego2global_rotation"])


def _single_frame_pickle(obj: object) -> bytes:
    """Protocol-5 bytes of a small object, re-framed so its strings can be edited."""
    data = pickle.dumps(obj, protocol=5)
    assert data[2] == 0x95  # PROTO 5, then one FRAME
    return data[11:]


def test_log_pickle_accepts_numpy_1_module_names(tmp_path: Path) -> None:
    body = _single_frame_pickle([{"token": "a", "values": np.arange(3.0), "scalar": np.float64(2.5)}])
    for new, old in (
        (b"numpy.core.numeric", b"numpy._core.numeric"),
        (b"numpy.core.multiarray", b"numpy._core.multiarray"),
    ):
        body = body.replace(bytes([0x8C, len(old)]) + old, bytes([0x8C, len(new)]) + new)
    assert b"numpy._core" not in body
    path = tmp_path / "old.pkl"
    path.write_bytes(b"\x80\x05\x95" + struct.pack("<Q", len(body)) + body)
    frames = load_log(path)
    np.testing.assert_array_equal(frames[0]["values"], [0.0, 1.0, 2.0])
    assert frames[0]["scalar"] == 2.5


class _Exploit:
    def __reduce__(self):
        return (os.getcwd, ())


@pytest.mark.parametrize(
    "payload, message",
    [
        (lambda: pickle.dumps([{"token": _Exploit()}], protocol=5), "posix.getcwd is not allowed"),
        (
            lambda: pickle.dumps([pickle.PickleBuffer(b"abc")], protocol=5, buffer_callback=lambda _: False),
            "out-of-band",
        ),
        (lambda: pickle.dumps({"not": "a list"}, protocol=5), "expected a list of frame dicts"),
        (lambda: b"not a pickle", "not a readable log pickle"),
    ],
)
def test_log_pickle_refuses_anything_but_frame_data(tmp_path: Path, payload, message: str) -> None:
    path = tmp_path / "bad.pkl"
    path.write_bytes(payload())
    with pytest.raises(LogFormatError, match=message) as error:
        load_log(path)
    assert str(path) in str(error.value)


# --- frames --------------------------------------------------------------------------------------


def test_quaternion_yaw_follows_pyquaternion() -> None:
    assert quaternion_yaw([math.cos(0.4), 0.0, 0.0, math.sin(0.4)]) == pytest.approx(0.8, abs=1e-15)
    # Not normalised: pyquaternion normalises first, so the yaw is unchanged.
    assert quaternion_yaw([2 * math.cos(-1.2), 0.0, 0.0, 2 * math.sin(-1.2)]) == pytest.approx(
        -2.4, abs=1e-15
    )
    # With roll and pitch the yaw is atan2(2(wz - xy), 1 - 2(y^2 + z^2)): note the minus (textbook has plus).
    w, x, y, z = 0.9, 0.2, 0.3, 0.25
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    expected = math.atan2(2 * (w * z - x * y), 1 - 2 * (y * y + z * z))
    assert quaternion_yaw([w, x, y, z]) == pytest.approx(expected, abs=1e-14)
    assert abs(expected - math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))) > 0.1


def test_frame_conversion_recovers_global_ground_truth() -> None:
    truth_frames = road_frames()
    for truth in truth_frames:
        if truth.roll_pitch != (0.0, 0.0):
            continue
        converted = convert_frame(log_frame(truth, "log"))
        assert converted["token"] == truth.token
        assert converted["timestamp_us"] == truth.timestamp
        ego = converted["ego"]
        assert (ego["x"], ego["y"]) == (truth.x, truth.y)
        assert ego["heading"] == pytest.approx(truth.yaw, abs=1e-14)
        assert [ego[k] for k in ("vx", "vy", "ax", "ay")] == list(truth.dynamics)
        assert converted["route_roadblocks"] == truth.route
        assert converted["traffic_lights"] == [[str(connector), is_red] for connector, is_red in truth.lights]
        assert all(isinstance(is_red, bool) for _, is_red in converted["traffic_lights"])
        assert [o["track"] for o in converted["objects"]] == [o.track for o in truth.objects]
        assert [o["category"] for o in converted["objects"]] == [o.name for o in truth.objects]
        for obj, expected in zip(converted["objects"], truth.objects, strict=True):
            x, y, z, length, width, height, heading = obj["box"]
            assert (x, y) == pytest.approx((expected.x, expected.y), abs=1e-8)
            assert (z, length, width, height) == pytest.approx((0.8, *expected.size), abs=1e-12)
            assert -math.pi < heading <= math.pi
            assert math.remainder(heading - expected.heading, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
            if expected.name in ("vehicle", "pedestrian", "bicycle"):
                assert obj["velocity"] == pytest.approx(list(expected.velocity), abs=1e-12)
            else:
                assert obj["velocity"] == [
                    0.0,
                    0.0,
                ]  # static objects carry no velocity, whatever the log says


def test_box_headings_beyond_pi_are_wrapped_only_after_adding_the_ego_yaw() -> None:
    truth = next(t for t in road_frames() if t.yaw < -0.05)
    frame = log_frame(truth, "log")
    bicycle = [o.track for o in truth.objects].index("oncoming")
    local_heading = frame["anns"]["gt_boxes"][bicycle, 6]
    assert local_heading > math.pi  # stored unwrapped, as the generator subtracts yaws
    converted = convert_frame(frame)["objects"][bicycle]["box"][6]
    assert converted == pytest.approx(3.13, abs=1e-12)


def test_boxes_are_placed_from_the_rear_axle_an_ego_state_reports() -> None:
    truth = road_frames()[3]
    frame = log_frame(truth, "log")
    pose = ego_pose(frame)
    rear_x, rear_y = rear_axle_round_trip(pose.x, pose.y, pose.heading)
    local = frame["anns"]["gt_boxes"][0]
    box = convert_frame(frame)["objects"][0]["box"]
    assert box[0] == (local[0] * np.cos(pose.heading) - local[1] * np.sin(pose.heading)) + rear_x
    assert box[1] == (local[0] * np.sin(pose.heading) + local[1] * np.cos(pose.heading)) + rear_y


def test_roll_and_pitch_use_the_2d_reconstruction_as_navsim_does() -> None:
    truth = road_frames()[7]
    assert truth.roll_pitch != (0.0, 0.0)
    converted = convert_frame(log_frame(truth, "log"))
    lead = converted["objects"][0]["box"]
    # The generator rotated boxes into the ego frame in 3-D; NAVSIM rotates back in 2-D only.
    assert 1e-6 < abs(lead[0] - truth.objects[0].x) < 0.05


def test_frame_errors_name_the_frame_and_key() -> None:
    truth = road_frames()[0]
    frame = log_frame(truth, "log")
    names = frame["anns"]["gt_names"].tolist()
    frame["anns"]["gt_names"] = np.array([names[0], "animal", *names[2:]])
    with pytest.raises(
        FrameError, match=rf"frame {truth.token}: anns.gt_names: unknown class\(es\) \['animal'\]"
    ):
        convert_frame(frame)
    frame = log_frame(truth, "log")
    frame["anns"]["track_tokens"] = frame["anns"]["track_tokens"][:2]
    with pytest.raises(FrameError, match="annotation lists differ in length"):
        convert_frame(frame)
    frame = log_frame(truth, "log", test_mode=True)
    with pytest.raises(FrameError, match=f"frame {truth.token}: anns: missing key"):
        convert_frame(frame)
    frame = log_frame(truth, "log")
    frame["ego_dynamic_state"] = [1.0, float("nan"), 0.0, 0.0]
    with pytest.raises(FrameError, match="ego_dynamic_state"):
        convert_frame(frame)


def test_a_frame_without_objects_converts() -> None:
    truth = road_frames()[1]
    truth.objects = []
    assert convert_frame(log_frame(truth, "log"))["objects"] == []


def test_stored_driving_command_is_kept_only_when_one_hot() -> None:
    truth = road_frames()[0]
    frame = log_frame(truth, "log")
    assert convert_frame(frame)["driving_command"] == [0, 1, 0, 0]
    frame["driving_command"] = np.array([0, 0, 0, 0])
    assert convert_frame(frame)["driving_command"] is None
    del frame["driving_command"]
    assert convert_frame(frame)["driving_command"] is None


def test_scene_windows_cut_like_navsim_filter_scenes() -> None:
    frames = [{"token": f"{k:016x}"} for k in range(40)]
    windows = list(scene_windows(frames, 1))
    assert len(windows) == 27 and windows[0] == (f"{3:016x}", 0) and windows[-1] == (f"{29:016x}", 26)
    assert [start for _, start in scene_windows(frames, 14)] == [0, 14]
    assert window_problem(frames, 3, 1) is None and window_problem(frames, 29, 1) is None
    assert "only 2 frame(s) before" in window_problem(frames, 2, 1)
    assert "only 9 frame(s) after" in window_problem(frames, 30, 1)
    assert "window position" in window_problem(frames, 4, 14)


# --- GeoPackage ----------------------------------------------------------------------------------


def test_map_locations_and_paths(maps_dir: Path, tmp_path: Path) -> None:
    assert map_location("las_vegas") == "us-nv-las-vegas-strip"
    with pytest.raises(MapFormatError, match="unknown map location 'mars'"):
        map_location("mars")
    assert gpkg_path(maps_dir, LOCATION).name == "map.gpkg"
    (tmp_path / LOCATION / "1.0").mkdir(parents=True)
    (tmp_path / LOCATION / "1.0" / "map.gpkg").write_bytes(b"")
    assert (
        gpkg_path(tmp_path, LOCATION) == tmp_path / LOCATION / "1.0" / "map.gpkg"
    )  # no version file: the only one
    with pytest.raises(MapFormatError, match="found 0"):
        gpkg_path(tmp_path, "sg-one-north")


def test_geopackage_layers_are_reprojected_to_the_meta_projected_system(tables) -> None:
    truth = road_map()
    for table, layer in (("lanes_polygons", tables.lanes), ("lane_groups_polygons", tables.roadblocks)):
        expected = {str(fid): geometry for fid, geometry, _ in truth[table].rows}
        assert set(layer.ids) == set(expected)
        for object_id, geometry in zip(layer.ids, layer.geometries, strict=True):
            coordinates = shapely.get_coordinates(geometry)
            np.testing.assert_allclose(
                coordinates, shapely.get_coordinates(expected[object_id]), rtol=0, atol=1e-6
            )
    assert tables.baselines[str(lane_id(3, 1))] == pytest.approx(
        np.array([[X0 + 150 + 10 * k, Y0 + 1.75] for k in range(5)]), abs=1e-6
    )


def test_geopackage_relations_follow_the_devkit(tables) -> None:
    assert tables.lane_outgoing[str(lane_id(5, 0))] == [str(lane_connector_id(5, 0))]
    assert tables.lane_incoming[str(lane_id(6, 1))] == [str(lane_connector_id(5, 1))]
    assert tables.roadblock_lanes[str(roadblock_id(7))] == [str(lane_id(7, 0)), str(lane_id(7, 1))]
    assert tables.roadblock_outgoing[str(roadblock_id(22))] == [str(connector_id(22)), str(TURN_CONNECTOR)]
    assert tables.roadblock_incoming[str(roadblock_id(23))] == [str(connector_id(22))]
    assert tables.roadblock_connector_lanes[str(connector_id(4))] == [
        str(lane_connector_id(4, 0)),
        str(lane_connector_id(4, 1)),
    ]
    speed = tables.lanes.attributes["speed_limit_mps"]
    assert speed[tables.lanes.row_of[str(lane_id(21, 1))]] is None
    assert speed[tables.lanes.row_of[str(lane_id(21, 0))]] == 13.4


def test_geopackage_in_projected_storage_is_read_unchanged_and_in_fid_order(tmp_path: Path) -> None:
    truth = road_map()
    path = tmp_path / "map.gpkg"
    write_gpkg(path, truth, storage_epsg=32611, reverse_rows=True)
    tables = load_map_tables(path, LOCATION)
    assert list(tables.roadblocks.ids) == sorted(tables.roadblocks.ids, key=int)
    expected = {str(fid): geometry for fid, geometry, _ in truth["lane_groups_polygons"].rows}
    assert all(
        shapely.equals_exact(g, expected[i], tolerance=0)
        for i, g in zip(tables.roadblocks.ids, tables.roadblocks.geometries, strict=True)
    )


def test_geopackage_errors_name_the_file(tmp_path: Path) -> None:
    path = tmp_path / "map.gpkg"
    write_gpkg(path, road_map(), projected="not a crs")
    with pytest.raises(MapFormatError, match=f"{path}: meta: projectedCoordSystem 'not a crs'"):
        load_map_tables(path, LOCATION)
    tables = road_map()
    del tables["walkways"]
    path = tmp_path / "other.gpkg"
    write_gpkg(path, tables)
    with pytest.raises(MapFormatError, match="table walkways: not a GeoPackage feature table"):
        load_map_tables(path, LOCATION)


# --- excerpts ------------------------------------------------------------------------------------

ROUTE = [str(i) for b in range(20, 23) for i in (roadblock_id(b), connector_id(b))] + [str(roadblock_id(23))]


def test_excerpt_holds_the_square_and_the_route_neighbourhood(tables) -> None:
    pose = EgoPose(X0 + 1005.0, Y0 + 1.75, 0.0)
    excerpt = build_excerpt(tables, pose, ROUTE)
    blocks = [block.id for block in excerpt.map.roadblocks]
    # Route blocks 20-23; 15 steps back from block 20 reach connector 12 (block 13 at step 14); 30 steps
    # forward from block 23 reach block 38 (connector 37 at step 29); block 22's turn leads north.
    expected_blocks = [roadblock_id(b) for b in range(13, 39)] + [ISOLATED_BLOCK, *NORTH_BLOCKS, SOUTH_BLOCK]
    assert blocks == [str(b) for b in sorted(expected_blocks)]  # table (fid) order
    expected_connectors = [connector_id(b) for b in range(12, 38)] + [
        TURN_CONNECTOR,
        NORTH_CONNECTOR,
        RIGHT_CONNECTOR,
    ]
    assert [c.id for c in excerpt.map.roadblock_connectors] == [str(c) for c in sorted(expected_connectors)]
    assert str(FAR_BLOCK) not in blocks
    # Every block brings all of its lanes, every roadblock connector all of its lane connectors.
    lane_blocks = {lane.roadblock for lane in excerpt.map.lanes}
    assert lane_blocks == {b for b in blocks if b != str(ISOLATED_BLOCK)}
    assert len(excerpt.map.lanes) == 2 * 26 + 3
    assert len(excerpt.map.lane_connectors) == 2 * 26 + 3
    areas = {
        name: [a.id for a in getattr(excerpt.map, name)]
        for name in ("carpark_areas", "drivable_areas", "crosswalks", "walkways", "intersections")
    }
    assert areas == {
        "carpark_areas": [str(CARPARK)],
        "drivable_areas": [str(DRIVABLE)],
        "crosswalks": [str(CROSSWALK)],
        "walkways": [str(WALKWAY)],
        "intersections": [str(intersection_id(i)) for i in range(18, 22)],
    }
    assert str(FAR_WALKWAY) not in areas["walkways"]


def test_excerpt_square_is_centred_on_the_ego_box_not_the_rear_axle(tables) -> None:
    # The far walkway ends at x0 + 3100; the rear axle stands 103 m east of it, beyond the 100 m square
    # plus its 2 m margin. Heading west, the box centre is 1.461 m closer and the walkway is in reach.
    west = EgoPose(X0 + 3203.0, Y0 + 1.75, math.pi)
    center_x, _ = ego_center(west.x, west.y, west.heading)
    assert west.x - center_x == pytest.approx(1.461)
    assert str(FAR_WALKWAY) in [w.id for w in build_excerpt(tables, west, []).map.walkways]
    east = EgoPose(X0 + 3203.0, Y0 + 1.75, 0.0)
    assert str(FAR_WALKWAY) not in [w.id for w in build_excerpt(tables, east, []).map.walkways]


def test_excerpt_holds_the_lanes_and_areas_at_every_current_vehicle(tables) -> None:
    # The junction (x0 + 1138 .. 1152) and the far walkway lie beyond the square around an ego at x0 + 960.
    pose = EgoPose(X0 + 960.0, Y0 + 1.75, 0.0)
    plain = build_excerpt(tables, pose, ROUTE).map
    assert str(INTERSECTION) not in [area.id for area in plain.intersections]
    vehicles = [(X0 + 1145.0, Y0 + 5.0), (X0 + 3050.0, Y0 - 1.0)]
    reactive = build_excerpt(tables, pose, ROUTE, vehicles).map
    assert str(INTERSECTION) in [area.id for area in reactive.intersections]
    assert str(FAR_WALKWAY) in [area.id for area in reactive.walkways]
    # A vehicle inside a lane brings the lane's roadblock with all its lanes.
    far_block = 59
    assert str(roadblock_id(far_block)) not in [block.id for block in plain.roadblocks]
    beside = build_excerpt(tables, pose, ROUTE, [(X0 + far_block * 50.0 + 20.0, Y0 + 1.75)]).map
    assert str(roadblock_id(far_block)) in [block.id for block in beside.roadblocks]
    assert {str(lane_id(far_block, side)) for side in (0, 1)} <= {lane.id for lane in beside.lanes}


def test_excerpt_lanes_and_graph_are_the_maps(tables) -> None:
    excerpt = build_excerpt(tables, EgoPose(X0 + 1005.0, Y0 + 1.75, 0.0), ROUTE)
    lanes = {lane.id: lane for lane in excerpt.map.lanes}
    lane = lanes[str(lane_id(22, 0))]
    assert lane.roadblock == str(roadblock_id(22))
    assert lane.outgoing == (str(lane_connector_id(22, 0)), "4500")
    assert lane.incoming == (str(lane_connector_id(21, 0)),)
    assert lanes[str(lane_id(21, 1))].speed_limit_mps is None
    connectors = {c.id: c for c in excerpt.map.lane_connectors}
    connector = connectors[str(lane_connector_id(20, 1))]
    assert (connector.incoming, connector.outgoing, connector.roadblock) == (
        (str(lane_id(20, 1)),),
        (str(lane_id(21, 1)),),
        str(connector_id(20)),
    )
    block = {b.id: b for b in excerpt.map.roadblocks}[str(roadblock_id(22))]
    assert block.outgoing == (str(connector_id(22)), str(TURN_CONNECTOR)) and block.lanes == (
        str(lane_id(22, 0)),
        str(lane_id(22, 1)),
    )
    # The polygons are the map's outer rings.
    assert shapely.equals_exact(
        lane.polygon, tables.lanes.geometries[tables.lanes.row_of[lane.id]], tolerance=0
    )


def test_excerpt_warns_about_what_format_v1_drops_and_serialises_to_a_valid_scene(tables) -> None:
    truth = road_frames()
    frames = [convert_frame(log_frame(t, "log")) for t in truth[:14]]
    for frame in frames:
        frame["driving_command"] = [0, 1, 0, 0]
    pose = EgoPose(X0 + 1100.0, Y0 + 1.75, 0.0)
    excerpt = build_excerpt(tables, pose, ROUTE)
    assert str(INTERSECTION) in [a.id for a in excerpt.map.intersections]
    assert excerpt.warnings == (
        f"intersections {INTERSECTION}: 1 hole(s) dropped (format v1 stores outer rings)",
    )
    raw = {
        "format": "navsim-lb/scene",
        "version": 1,
        "token": frames[3]["token"],
        "log_name": "log",
        "map_name": LOCATION,
        "frame_interval_s": 0.5,
        "current_index": 3,
        "frames": frames,
        "map": excerpt_to_json(excerpt.map),
    }
    scene = parse_scene(raw, "fixture")
    assert [lane.id for lane in scene.map.lanes] == [lane.id for lane in excerpt.map.lanes]
    assert all(
        shapely.equals_exact(a.polygon, b.polygon, tolerance=0)
        for a, b in zip(scene.map.roadblocks, excerpt.map.roadblocks, strict=True)
    )


def test_excerpt_refuses_a_route_id_the_map_lacks(tables) -> None:
    with pytest.raises(MapFormatError, match="route roadblock 999999 is neither"):
        build_excerpt(tables, EgoPose(X0 + 1005.0, Y0 + 1.75, 0.0), ["999999"])
