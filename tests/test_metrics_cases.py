"""Hand-built cases whose metric values follow from the spec by hand.

The road: x from -60 to 160 m, lane "right" (on the route) y in [-3.5, 0], lane "left" y in [0, 3.5],
one roadblock over both. The ego drives along +x; its rear axle at (x, y) puts its box corners at
x - 1.127 ... x + 4.049 and y - 1.1485 ... y + 1.1485. Objects are boxes with a centre pose at each of
the 51 observation steps.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from engine_scoring import score_proposals

from scorer.drivable_map import DrivableMap
from scorer.geometry import REAR_AXLE_TO_CENTER, box_corners
from scorer.metrics.ego_areas import EgoArea
from scorer.observation import OBSERVATION_STEPS, Observation
from scorer.pdm_scorer import ProposalScores
from scorer.trajectory import STATE_SIZE, StateIndex
from scorer.versions import ScorerConfig, get_version

STEPS = 41
RIGHT_LANE_Y = -1.75  # rear-axle y that centres the ego in the right lane
V1_0, V1_1 = get_version("v1.0").evaluation, get_version("v1.1").evaluation


def drive(speed: float, y: float = RIGHT_LANE_Y, x0: float = 0.0, heading: float = 0.0) -> np.ndarray:
    """Return states (41, 11) at constant speed along `heading`, rear axle starting at (x0, y)."""
    travelled = np.arange(STEPS) * (speed * 0.1)
    states = np.zeros((STEPS, STATE_SIZE))
    states[:, StateIndex.X] = x0 + travelled * math.cos(heading)
    states[:, StateIndex.Y] = y + travelled * math.sin(heading)
    states[:, StateIndex.HEADING] = heading
    states[:, StateIndex.VELOCITY_X] = speed
    return states


def track(
    token: str,
    xs: np.ndarray | float,
    y: float,
    speed: float = 0.0,
    category: str = "vehicle",
    length: float = 5.0,
    width: float = 2.0,
) -> tuple:
    """Return an object: centre x per observation step (or one x for all), y, speed and box size."""
    xs = np.broadcast_to(np.asarray(xs, dtype=np.float64), (OBSERVATION_STEPS,))
    return token, category, xs, y, speed, length, width


def observe(*tracks: tuple) -> Observation:
    """Return an observation in which every object is present at all 51 steps."""
    corners = np.empty((OBSERVATION_STEPS, len(tracks), 4, 2))
    for index, (_, _, xs, y, _, length, width) in enumerate(tracks):
        corners[:, index] = box_corners(xs, np.full_like(xs, y), 0.0, length / 2.0, width / 2.0)
    is_agent = np.array(
        [category in ("vehicle", "pedestrian", "bicycle") for _, category, *_ in tracks], bool
    )
    return Observation(
        tokens=tuple(token for token, *_ in tracks),
        object_types=tuple(category.upper() for _, category, *_ in tracks),
        is_agent=is_agent,
        first_speed=np.array([speed for *_, speed, _, _ in tracks], dtype=np.float64),
        present=np.ones((OBSERVATION_STEPS, len(tracks)), dtype=bool),
        boxes=corners.reshape(-1, 4, 2),
    )


def rectangle(y_min: float, y_max: float, x_min: float = -60.0, x_max: float = 160.0) -> shapely.Polygon:
    return shapely.box(x_min, y_min, x_max, y_max)


def road(
    roadblock: shapely.Polygon | None = None, lanes: dict[str, tuple[float, float]] | None = None
) -> DrivableMap:
    """Return a map of one roadblock (default y in [-3.5, 3.5]) and its lanes (default right and left)."""
    lanes = {"right": (-3.5, 0.0), "left": (0.0, 3.5)} if lanes is None else lanes
    polygons = [rectangle(-3.5, 3.5) if roadblock is None else roadblock]
    polygons += [rectangle(*extent) for extent in lanes.values()]
    array = np.empty(len(polygons), dtype=object)
    array[:] = polygons
    return DrivableMap(tokens=("block", *lanes), types=("ROADBLOCK", *["LANE"] * len(lanes)), built=array)


CENTERLINE = np.array([[-60.0, RIGHT_LANE_Y], [160.0, RIGHT_LANE_Y]])


def score(
    *proposals: np.ndarray,
    objects: Observation | None = None,
    drivable_map: DrivableMap | None = None,
    route: tuple[str, ...] = ("right",),
    config: ScorerConfig = V1_1,
) -> ProposalScores:
    return score_proposals(
        np.stack(proposals),
        observe() if objects is None else objects,
        road() if drivable_map is None else drivable_map,
        CENTERLINE,
        route,
        config,
    )


# --- no at-fault collisions (NC) -----------------------------------------------------------------------


def test_running_into_a_stopped_vehicle_is_at_fault_and_zeroes_nc() -> None:
    # Ego front at 0.5 k + 4.049 reaches the vehicle's rear (15 - 2.5) at k = 17.
    scores = score(drive(5.0), objects=observe(track("car", 15.0, RIGHT_LANE_Y)))
    assert scores.no_at_fault_collisions[0] == 0.0
    assert scores.collision_index[0] == 17 and scores.collision_object[0] == 0
    assert scores.score[0] == 0.0


def test_running_into_a_cone_halves_nc() -> None:
    # The cone's rear (15 - 0.25) is reached at k = 22 (0.5 k + 4.049 >= 14.75).
    cone = track("cone", 15.0, RIGHT_LANE_Y, category="traffic_cone", length=0.5, width=0.5)
    scores = score(drive(5.0), objects=observe(cone))
    assert scores.no_at_fault_collisions[0] == 0.5
    assert scores.collision_index[0] == 22


def test_being_rear_ended_while_stopped_is_never_at_fault() -> None:
    # A car from behind at 5 m/s: its front (-20 + 0.5 k + 2.5) passes the ego's rear (-1.127) at k = 33.
    chaser = track("chaser", -20.0 + 0.5 * np.arange(OBSERVATION_STEPS), RIGHT_LANE_Y, speed=5.0)
    scores = score(drive(0.0), objects=observe(chaser))
    assert scores.no_at_fault_collisions[0] == 1.0
    assert scores.collision_index[0] == -1 and scores.collision_object[0] == -1
    assert scores.time_to_collision_within_bound[0] == 1.0  # TTC skips a standing ego


def test_being_rear_ended_while_moving_is_not_at_fault_either() -> None:
    chaser = track("chaser", -20.0 + 0.8 * np.arange(OBSERVATION_STEPS), RIGHT_LANE_Y, speed=8.0)
    assert score(drive(2.0), objects=observe(chaser)).no_at_fault_collisions[0] == 1.0


def _side_by_side(ego_y: float) -> ProposalScores:
    """A car driving along the ego's left side, its box 0.1 m into the ego's, centred beside the ego's centre."""
    xs = 0.5 * np.arange(OBSERVATION_STEPS) + REAR_AXLE_TO_CENTER
    neighbour = track("neighbour", xs, ego_y + 1.1485 + 1.0 - 0.1, speed=5.0)
    return score(drive(5.0, y=ego_y), objects=observe(neighbour))


def test_a_lateral_contact_is_at_fault_while_straddling_lanes() -> None:
    scores = _side_by_side(ego_y=0.0)
    assert scores.ego_areas[0, :, EgoArea.MULTIPLE_LANES].all()
    assert scores.no_at_fault_collisions[0] == 0.0
    assert scores.collision_index[0] == 0
    assert scores.time_to_collision_within_bound[0] == 0.0  # beside, not behind, while straddling


def test_a_lateral_contact_within_one_lane_is_not_at_fault() -> None:
    scores = _side_by_side(ego_y=RIGHT_LANE_Y)
    assert not scores.ego_areas[0, :, EgoArea.MULTIPLE_LANES].any()
    assert scores.no_at_fault_collisions[0] == 1.0
    assert scores.time_to_collision_within_bound[0] == 1.0


def test_a_token_cleared_once_stays_ignored_but_other_tokens_count() -> None:
    # The ego stands for 1 s touching car "a" (not at fault: "a" is ignored from then on), then drives
    # through it and on into the stopped car "b".
    states = drive(5.0, x0=-5.0)
    states[:11, StateIndex.X], states[:11, StateIndex.VELOCITY_X] = -5.0, 0.0
    states[11:, StateIndex.X] = -5.0 + 0.5 * np.arange(1, STEPS - 10)
    scores = score(states, objects=observe(track("a", 1.0, RIGHT_LANE_Y), track("b", 16.0, RIGHT_LANE_Y)))
    # "b" (rear at 13.5) is reached when -5 + 0.5 (k - 10) + 4.049 >= 13.5, i.e. k = 39.
    assert scores.no_at_fault_collisions[0] == 0.0
    assert scores.collision_index[0] == 39


# --- drivable area (DAC) ---------------------------------------------------------------------------------


def test_a_corner_on_the_road_edge_is_off_the_drivable_area() -> None:
    # Heading 0 puts the right corners at exactly y = -1.1485: on the boundary, hence outside.
    on_edge = score(drive(5.0, y=0.0), drivable_map=road(rectangle(-1.1485, 3.5)))
    inside = score(drive(5.0, y=0.0), drivable_map=road(rectangle(-1.15, 3.5)))
    assert on_edge.drivable_area_compliance[0] == 0.0
    assert on_edge.ego_areas[0, :, EgoArea.NON_DRIVABLE_AREA].all()
    assert on_edge.score[0] == 0.0
    assert inside.drivable_area_compliance[0] == 1.0


def test_lanes_alone_are_not_drivable_and_index_0_counts() -> None:
    lanes_only = DrivableMap(tokens=("right",), types=("LANE",), built=np.array([rectangle(-3.5, 0.0)]))
    assert score(drive(5.0), drivable_map=lanes_only).drivable_area_compliance[0] == 0.0
    # Only the first two poses poke out of the road's start at x = 0 (rear at 0.5 + 0.5 k - 1.127): DAC 0.
    starts_late = road(rectangle(-3.5, 3.5, x_min=0.0))
    scores = score(drive(5.0, x0=0.5), drivable_map=starts_late)
    assert scores.ego_areas[0, :, EgoArea.NON_DRIVABLE_AREA].tolist() == [True, True] + [False] * 39
    assert scores.drivable_area_compliance[0] == 0.0


# --- time to collision (TTC) -----------------------------------------------------------------------------


def test_ttc_fails_on_a_slower_agent_ahead_without_a_collision() -> None:
    # Lead rear at 13 + 0.3 m (map m), ego front at 4.049 + 0.5 k + 0.5 f: the gap stays positive over
    # 4 s (>= 0.951 m) but the 0.9 s projection first closes it at k = 36 (k + f >= 44.755, f <= 9).
    lead = track("lead", 15.5 + 0.3 * np.arange(OBSERVATION_STEPS), RIGHT_LANE_Y, speed=3.0)
    scores = score(drive(5.0), objects=observe(lead))
    assert scores.no_at_fault_collisions[0] == 1.0
    assert scores.time_to_collision_within_bound[0] == 0.0
    assert scores.ttc_index[0] == 36


def test_ttc_projects_a_reversing_ego_forward() -> None:
    # Reversing at 5 m/s (vx = -5, heading 0): TTC pushes the box along +x by |v| dt, onto a car just ahead.
    states = drive(-5.0)
    car = track("car", 4.049 + 2.5 + 1.0, RIGHT_LANE_Y, speed=0.0)  # 1 m ahead of the front bumper
    scores = score(states, objects=observe(car))
    assert scores.time_to_collision_within_bound[0] == 0.0
    assert scores.ttc_index[0] == 0
    assert scores.no_at_fault_collisions[0] == 1.0


# --- comfort ---------------------------------------------------------------------------------------------


def test_a_zig_zag_is_uncomfortable_and_a_steady_drive_is_comfortable() -> None:
    zigzag = drive(5.0)
    zigzag[:, StateIndex.HEADING] = 0.2 * (-1.0) ** np.arange(STEPS)
    scores = score(drive(5.0), zigzag)
    assert scores.comfort.tolist() == [1.0, 0.0]


def test_a_steady_brake_beyond_4_05_m_s2_is_uncomfortable() -> None:
    # A constant series passes every Savitzky-Golay filter unchanged: -5 is outside (-4.05, 2.40), -4 inside.
    hard, firm = drive(5.0), drive(5.0)
    hard[:, StateIndex.ACCELERATION_X], firm[:, StateIndex.ACCELERATION_X] = -5.0, -4.0
    assert score(hard, firm).comfort.tolist() == [0.0, 1.0]


def test_headings_wrapping_at_pi_stay_comfortable_and_make_progress_backwards() -> None:
    # Driving along -x with the heading flipping between pi - 1e-3 and -pi + 1e-3 every step.
    states = drive(5.0, x0=60.0, heading=math.pi)
    states[:, StateIndex.HEADING] = np.where(np.arange(STEPS) % 2 == 0, math.pi - 1e-3, -math.pi + 1e-3)
    scores = score(states)
    assert scores.comfort[0] == 1.0
    assert scores.drivable_area_compliance[0] == 1.0
    assert scores.progress_raw[0] == 0.0  # the centerline runs along +x: backwards is no progress


# --- ego progress (EP) and aggregation ------------------------------------------------------------------


def test_progress_is_normalised_by_the_best_multiplied_progress() -> None:
    # Spec 8: reference 25 m (multipliers 1), agent 20 m with NC 0.5 -> EP 0.4 and score 0.375.
    # The cone touches the agent's left side from index 0 (at fault: static), 42.7 degrees off its
    # heading and within its lane, so TTC puts it on the ignore-list at once.
    cone = track(
        "cone", REAR_AXLE_TO_CENTER, -0.6015 + 0.25 - 0.05, category="traffic_cone", length=0.5, width=0.5
    )
    scores = score(drive(6.25, y=1.75), drive(5.0), objects=observe(cone))
    assert scores.progress_raw == pytest.approx([25.0, 20.0], rel=1e-12)
    assert scores.no_at_fault_collisions.tolist() == [1.0, 0.5]
    assert scores.time_to_collision_within_bound.tolist() == [1.0, 1.0]
    assert scores.ego_progress[1] == pytest.approx(0.4, rel=1e-12)
    assert scores.score[1] == pytest.approx(0.375, rel=1e-12)


def test_below_the_5_m_threshold_every_proposal_with_a_multiplier_gets_ep_1() -> None:
    off_road = drive(0.8, y=10.0)
    scores = score(drive(0.8), drive(1.0), off_road)  # 3.2 m, 4.0 m, 3.2 m off the road
    assert scores.ego_progress.tolist() == [1.0, 1.0, 0.0]
    # PDM-Closed's v1.0 planner scorer normalises from 0.1 m on.
    planner = score(drive(0.8), drive(1.0), off_road, config=get_version("v1.0").planner)
    assert planner.ego_progress[:2] == pytest.approx([0.8, 1.0], rel=1e-12)


def test_above_the_threshold_progress_is_relative() -> None:
    scores = score(drive(1.5), drive(0.75))  # 6 m and 3 m
    assert scores.ego_progress == pytest.approx([1.0, 0.5], rel=1e-12)
    assert scores.score[1] == pytest.approx((5 * 0.5 + 5 + 2) / 12, rel=1e-12)


def test_a_standstill_ego_gets_no_progress_when_the_reference_moves() -> None:
    scores = score(drive(6.25), drive(0.0))
    assert scores.progress_raw[1] == 0.0
    assert scores.ego_progress[1] == 0.0
    assert scores.comfort[1] == 1.0
    assert scores.score[1] == pytest.approx(7.0 / 12.0, rel=1e-12)
    both_stand = score(drive(0.0), drive(0.0))
    assert both_stand.ego_progress.tolist() == [1.0, 1.0]
    assert both_stand.score.tolist() == [1.0, 1.0]


# --- driving direction (DDC) -----------------------------------------------------------------------------


def test_v1_0_sums_ddc_over_proposals_as_a_multiplier_and_v1_1_weighs_it_0() -> None:
    # Both off the route, 1.2 and 0.9 m per step (spec 7.3's worked example).
    reference, agent = drive(12.0, y=1.75), drive(9.0, y=1.75)
    v1_0 = score(reference, agent, config=V1_0)
    v1_1 = score(reference, agent, config=V1_1)
    assert v1_0.ego_areas[:, 1:, EgoArea.ONCOMING_TRAFFIC].all()
    assert v1_0.driving_direction_compliance.tolist() == [1.0, 0.5]  # max 1.2 m; max 1.2 + 0.9 = 2.1 m
    assert v1_1.driving_direction_compliance.tolist() == [0.0, 0.0]  # 11 x 1.2 m; 11 x 0.9 m
    # v1.0: the agent's multiplier 0.5 scales its progress (36 m -> 18 m of 48 m) and its score.
    assert v1_0.ego_progress[1] == pytest.approx(18.0 / 48.0, rel=1e-12)
    assert v1_0.score[1] == pytest.approx(0.5 * (5 * 18.0 / 48.0 + 5 + 2) / 12, rel=1e-12)
    assert v1_1.ego_progress[1] == pytest.approx(36.0 / 48.0, rel=1e-12)
    assert v1_1.score[1] == pytest.approx((5 * 36.0 / 48.0 + 5 + 2) / 12, rel=1e-12)


def test_the_v1_0_window_spans_11_proposals() -> None:
    # 12 proposals each 0.52 m off route per step: proposal p sums min(p + 1, 11) of them.
    scores = score(*[drive(5.2, y=1.75)] * 12, config=V1_0)
    assert scores.driving_direction_compliance.tolist() == [1.0] * 3 + [0.5] * 9  # 11 x 0.52 = 5.72 < 6


def test_on_the_route_there_is_no_off_route_distance() -> None:
    scores = score(drive(12.0), config=V1_0)
    assert not scores.ego_areas[0, :, EgoArea.ONCOMING_TRAFFIC].any()
    assert scores.driving_direction_compliance[0] == 1.0


# --- empty inputs ----------------------------------------------------------------------------------------


def test_an_empty_observation_and_map() -> None:
    empty_map = DrivableMap(tokens=(), types=(), built=np.empty(0, dtype=object))
    scores = score(drive(5.0), objects=observe(), drivable_map=empty_map)
    assert scores.no_at_fault_collisions[0] == 1.0
    assert scores.time_to_collision_within_bound[0] == 1.0
    assert scores.drivable_area_compliance[0] == 0.0
    assert scores.ego_areas[0, :, EgoArea.ONCOMING_TRAFFIC].all()


# Branches the reference scenes do not pin. NAVSIM calls nuPlan's `is_agent_ahead` and `is_track_stopped`
# with their defaults: 30 degrees and 0.05 m/s in nuplan-devkit v1.2 (older nuPlan had 20 degrees and
# 5e-3, which would flip the first two cases).


def test_ttc_counts_an_object_25_degrees_off_the_heading_as_ahead() -> None:
    # Ego at 5 m/s along +x in the right lane (one lane, drivable, no intersection). A 1 x 0.5 m vehicle
    # moves with it, centroid 2.8 m ahead of and 1.3 m left of the rear axle: atan2(1.3, 2.8) = 24.9 deg.
    # Its box (y in [-0.7, -0.2]) overlaps the ego box (top y = -0.6015) at every step.
    # NC: moving vehicle, not behind, front bumper (x = +4.049) misses it (x <= +3.3) -> lateral, single
    # lane -> not at fault -> ignored; NC = 1.
    # TTC at k = 0, f = 0: speed 5 >= 5e-3, angle 24.9 deg < 30 deg -> is_agent_ahead -> TTC = 0 at k = 0.
    # (With nuPlan's old 20 deg default: not ahead, not in a critical area -> ignored -> TTC = 1.)
    assert math.degrees(math.atan2(1.3, 2.8)) < 30.0
    xs = 2.8 + 0.5 * np.arange(OBSERVATION_STEPS)
    buddy = track("buddy", xs, RIGHT_LANE_Y + 1.3, speed=5.0, length=1.0, width=0.5)
    scores = score(drive(5.0), objects=observe(buddy))
    assert scores.no_at_fault_collisions[0] == 1.0
    assert scores.time_to_collision_within_bound[0] == 0.0
    assert scores.ttc_index[0] == 0


def test_a_vehicle_creeping_at_0_03_m_s_is_a_stopped_track() -> None:
    # A 5 x 2 m vehicle beside the ego (centre x = ego centre, 0.1 m overlap on the left), first-sighting
    # speed 0.03 m/s. get_collision_type: ego 5 m/s > 0.05 (not stopped); is_track_stopped: 0.03 <= 0.05
    # -> STOPPED_TRACK_COLLISION -> at fault, vehicle -> NC = 0 at k = 0.
    # (With nuPlan's old 5e-03 default: lateral in one lane -> not at fault -> NC = 1.)
    neighbour = track("creeper", REAR_AXLE_TO_CENTER, RIGHT_LANE_Y + 1.1485 + 1.0 - 0.1, speed=0.03)
    scores = score(drive(5.0), objects=observe(neighbour))
    assert scores.no_at_fault_collisions[0] == 0.0
    assert scores.collision_index[0] == 0


def test_a_centroid_on_the_rear_axle_gives_a_nan_angle_and_a_lateral_contact() -> None:
    # A 1 x 1 m pedestrian moving with the ego, centred exactly on the rear axle: get_agent_relative_angle
    # divides by a zero norm -> NaN; is_agent_behind(NaN > 150 deg) is False; the front bumper misses it ->
    # ACTIVE_LATERAL; single lane, drivable -> not at fault -> NC = 1. TTC: NaN < 30 deg is False, not in a
    # critical area -> ignored -> TTC = 1.
    walker = track(
        "walker",
        0.5 * np.arange(OBSERVATION_STEPS),
        RIGHT_LANE_Y,
        speed=5.0,
        category="pedestrian",
        length=1.0,
        width=1.0,
    )
    scores = score(drive(5.0), objects=observe(walker))
    assert scores.no_at_fault_collisions[0] == 1.0
    assert scores.time_to_collision_within_bound[0] == 1.0
