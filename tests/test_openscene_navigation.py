"""Navigation goal (driving command) from the route centerline, as OpenScene's generator computes it."""

from __future__ import annotations

import pytest
from openscene_builders import (
    LOCATION,
    NORTH_BLOCKS,
    NORTH_CONNECTOR,
    RIGHT_CONNECTOR,
    SOUTH_BLOCK,
    TURN_CONNECTOR,
    X0,
    Y0,
    connector_id,
    roadblock_id,
    write_maps,
)

from scorer.openscene.excerpt import build_excerpt
from scorer.openscene.frames import EgoPose
from scorer.openscene.gpkg import gpkg_path, load_map_tables
from scorer.openscene.navigation import LEFT, RIGHT, STRAIGHT, UNKNOWN, navigation_command


@pytest.fixture(scope="module")
def tables(tmp_path_factory: pytest.TempPathFactory):
    maps = tmp_path_factory.mktemp("maps")
    write_maps(maps)
    return load_map_tables(gpkg_path(maps, LOCATION), LOCATION)


def command(tables, x: float, y: float, heading: float, route: list[int]) -> list[int]:
    pose = EgoPose(X0 + x, Y0 + y, heading)
    ids = [str(block) for block in route]
    return navigation_command(build_excerpt(tables, pose, ids).map, pose, ids)


STRAIGHT_ROUTE = [roadblock_id(20), connector_id(20), roadblock_id(21), connector_id(21), roadblock_id(22)]
LEFT_ROUTE = [roadblock_id(22), TURN_CONNECTOR, NORTH_BLOCKS[0], NORTH_CONNECTOR, NORTH_BLOCKS[1]]
RIGHT_ROUTE = [roadblock_id(30), RIGHT_CONNECTOR, SOUTH_BLOCK]


def test_straight_road_gives_straight(tables) -> None:
    assert command(tables, 1005.0, 1.75, 0.0, STRAIGHT_ROUTE) == STRAIGHT


def test_turn_within_20_m_gives_left_or_right(tables) -> None:
    # Roadblock 22 ends at x = 1140: from x = 1130 the point 20 m ahead is well into the left turn.
    assert command(tables, 1130.0, 5.25, 0.0, LEFT_ROUTE) == LEFT
    assert command(tables, 1530.0, 1.75, 0.0, RIGHT_ROUTE) == RIGHT


def test_turn_beyond_20_m_is_still_straight(tables) -> None:
    assert command(tables, 1105.0, 5.25, 0.0, LEFT_ROUTE) == STRAIGHT


def test_no_route_gives_unknown(tables) -> None:
    assert command(tables, 1005.0, 1.75, 0.0, []) == UNKNOWN


def test_off_route_without_a_way_back_gives_unknown(tables) -> None:
    # From roadblock 10 the route (north of roadblock 22) is 27 steps ahead: PDM-Closed's forward search
    # would reach it, OpenScene's generator only searches backward from the route (15 steps) and gives up.
    assert command(tables, 505.0, 1.75, 0.0, [NORTH_BLOCKS[0], NORTH_CONNECTOR, NORTH_BLOCKS[1]]) == UNKNOWN


def test_ego_just_behind_the_route_is_attached_to_it(tables) -> None:
    # Starting one roadblock before the route: the backward search links it, and the turn is 20 m ahead.
    assert command(tables, 1095.0, 5.25, 0.0, [TURN_CONNECTOR, NORTH_BLOCKS[0]]) == STRAIGHT
    assert command(tables, 1135.0, 5.25, 0.0, [TURN_CONNECTOR, NORTH_BLOCKS[0]]) == LEFT
