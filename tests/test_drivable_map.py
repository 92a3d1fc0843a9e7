"""The drivable-area map: square proximity around the ego box centre, layer order, what counts (spec 5)."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from scorer.drivable_map import DrivableMap, MapBatch, build_drivable_map, proximal_mask
from scorer.geometry import REAR_AXLE_TO_CENTER
from scorer.metrics.pairs import points_inside
from scorer.scene import Area, EgoStatus, Frame, Lane, MapExcerpt, Roadblock, Scene

CENTER_X = 0.0 + REAR_AXLE_TO_CENTER  # the ego's rear axle is at the origin, heading 0
EDGE = CENTER_X + 100.0  # right edge of the proximity square, as the devkit computes it


def block(block_id: str, x_min: float, x_max: float, y_min: float = -5.0, y_max: float = 5.0) -> Roadblock:
    return Roadblock(block_id, shapely.box(x_min, y_min, x_max, y_max), (), (), ())


def lane(lane_id: str, roadblock: str, x_min: float, x_max: float) -> Lane:
    polygon = shapely.box(x_min, -2.0, x_max, 2.0)
    return Lane(lane_id, polygon, roadblock, np.array([[x_min, 0.0], [x_max, 0.0]]), None, (), ())


def area(area_id: str, x_min: float, x_max: float) -> Area:
    return Area(area_id, shapely.box(x_min, -5.0, x_max, 5.0))


def scene_on(excerpt: MapExcerpt) -> Scene:
    frame = Frame(
        token="frame",
        timestamp_us=0,
        ego=EgoStatus(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        driving_command=(0, 1, 0, 0),
        tracks=(),
        categories=(),
        boxes=np.zeros((0, 7)),
        velocities=np.zeros((0, 2)),
        traffic_lights=(),
        route_roadblocks=(),
    )
    return Scene("scene", "log", "map", 0.5, 0, (frame,) * 11, excerpt)


def by_type(excerpt: MapExcerpt) -> dict[str, list[str]]:
    drivable_map = build_drivable_map(scene_on(excerpt))
    grouped: dict[str, list[str]] = {}
    for token, kind in zip(drivable_map.tokens, drivable_map.types, strict=True):
        grouped.setdefault(kind, []).append(token)
    return grouped


def test_proximity_is_a_square_around_the_box_centre_and_touching_counts() -> None:
    excerpt = MapExcerpt(
        lanes=(),
        lane_connectors=(),
        roadblocks=(
            block("touching", EDGE, EDGE + 10.0),
            block("beyond", EDGE + 0.01, EDGE + 10.0),
            block("diagonal", 80.0, 90.0, 80.0, 90.0),  # 113 m away, yet inside the square
            block("behind_rear_axle", -99.0, -98.6),  # within 100 m of the rear axle, not of the centre
        ),
        roadblock_connectors=(),
    )
    assert by_type(excerpt) == {"ROADBLOCK": ["touching", "diagonal"]}


def test_polygons_come_in_the_devkits_layer_order_and_only_drivable_layers() -> None:
    excerpt = MapExcerpt(
        lanes=(
            lane("l2", "b1", 0.0, 10.0),
            lane("far_lane", "far", 0.0, 10.0),
            lane("l1", "b1", 0.0, 10.0),
            lane("l3", "b0", -10.0, 0.0),
        ),
        lane_connectors=(lane("c1", "rc", 10.0, 12.0),),
        roadblocks=(block("b1", 0.0, 10.0), block("far", 500.0, 510.0), block("b0", -10.0, 0.0)),
        roadblock_connectors=(block("rc", 10.0, 12.0),),
        intersections=(area("i", 10.0, 12.0),),
        carpark_areas=(area("p", 20.0, 30.0),),
        drivable_areas=(area("generic", -5.0, 5.0),),
        crosswalks=(area("zebra", 0.0, 2.0),),
        walkways=(area("path", 0.0, 2.0),),
    )
    drivable_map = build_drivable_map(scene_on(excerpt))
    # Roadblocks; each near roadblock's lanes in lane-layer order; connector lanes (not the connector itself);
    # intersections; car parks. A far roadblock's lanes stay out even where the lane itself is near.
    assert drivable_map.tokens == ("b1", "b0", "l2", "l1", "l3", "c1", "i", "p")
    assert drivable_map.types == (
        "ROADBLOCK",
        "ROADBLOCK",
        "LANE",
        "LANE",
        "LANE",
        "LANE_CONNECTOR",
        "INTERSECTION",
        "CARPARK_AREA",
    )


def test_the_centre_follows_the_heading() -> None:
    # Heading pi: the box centre is 1.461 m behind the origin along -x, so the square reaches x = -101.461.
    excerpt = MapExcerpt((), (), (block("west", -101.461 - 0.001, -101.0), block("east", 98.6, 99.0)), ())
    scene = scene_on(excerpt)
    turned = scene.frames[0]._replace(ego=EgoStatus(0.0, 0.0, np.pi, 0.0, 0.0, 0.0, 0.0))
    drivable_map = build_drivable_map(scene._replace(frames=(turned,) * 11))
    assert drivable_map.tokens == ("west",)


def test_proximal_mask_tests_any_square() -> None:
    polygons = np.array(
        [
            shapely.box(1.0, 1.0, 2.0, 2.0),
            shapely.box(3.0, 3.0, 4.0, 4.0),
            shapely.Point(0.5, 0.5).buffer(0.1),
        ]
    )
    assert proximal_mask(polygons, 0.0, 0.0, 1.0).tolist() == [True, False, True]
    assert proximal_mask(polygons, 0.0, 0.0, 0.99).tolist() == [False, False, True]


def test_points_on_a_boundary_are_outside() -> None:
    maps = MapBatch.of([build_drivable_map(scene_on(MapExcerpt((), (), (block("b", 0.0, 10.0),), ())))], [()])
    x, y = np.array([5.0, 0.0, 10.0, 11.0]), np.array([0.0, 0.0, 5.0, 0.0])
    assert points_inside(x, y, np.zeros(4, dtype=np.intp), maps).tolist() == [True, False, False, False]


def test_a_stored_map_builds_only_the_polygons_a_test_reads() -> None:
    blocks = (block("a", 0.0, 10.0), block("b", 10.0, 20.0), block("c", 20.0, 30.0))
    lanes = (lane("1", "a", 0.0, 10.0), lane("2", "b", 10.0, 20.0))
    scene_map = build_drivable_map(scene_on(MapExcerpt(lanes, (), blocks, ())))
    stored = DrivableMap(scene_map.tokens, scene_map.types, stored=scene_map.outlines)
    built, read = MapBatch.of([scene_map], [()]), MapBatch.of([scene_map, stored], [(), ()])
    assert np.array_equal(read.bounds, np.concatenate([shapely.bounds(scene_map.polygons)] * 2))
    assert shapely.is_missing(read.polygons).tolist() == [False] * 5 + [True] * 5
    # Polygons a, b, c, 1, 2: a point inside a, one on b's boundary, points outside c's and lane 2's boxes.
    x, y = np.array([5.0, 10.0, 15.0, 5.0, 15.0]), np.array([0.0, 0.0, 0.0, 1.0, 3.0])
    polygon = np.arange(5)
    inside = points_inside(x, y, polygon, built).tolist()
    assert inside == [True, False, False, True, False]
    assert points_inside(x, y, polygon + 5, read).tolist() == inside
    assert shapely.is_missing(read.polygons[5:]).tolist() == [False, False, True, False, True]
    assert shapely.equals_exact(read.polygons[5], scene_map.polygons[0], 0.0)
    assert shapely.is_prepared(read.polygons[5])
    assert shapely.equals_exact(stored.polygons, scene_map.polygons, 0.0).all()
    with pytest.raises(ValueError, match="its polygons or from their outlines"):
        DrivableMap(scene_map.tokens, scene_map.types)
