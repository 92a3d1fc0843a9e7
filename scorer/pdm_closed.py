"""The PDM-Closed reference trajectory of a scene, as NAVSIM's metric caching computes it
(docs/engine.md, "PDM-Closed").

One planning iteration: route correction and centerline (`scorer.route`), the forecast observation
(`scorer.planner_observation`), 15 IDM proposals (3 paths: the centerline and its -1 m / +1 m
offsets, x 5 target speeds), simulated (`scorer.simulation`) and scored with the version's
planner scorer (`scorer.pdm_scorer`); the best one, extended to 5 s, is the cached trajectory.

The IDM unroll mirrors `PDMGenerator` including its quirks: the leading agent is
searched at even time indices only and index 1 copies the never-filled index 0 (so the first step
brakes against a phantom obstacle at progress 0), and the 3-value leading-agent buffer is shared by
the proposals of a path within a step, so values a proposal does not write are those of the previous
proposal (the selected proposal's extension to 5 s runs alone, from a fresh buffer). See
docs/engine.md, "PDM-Closed: the IDM unroll".

Headings the devkit keeps (path poses, the leading agent's relative heading) are wrapped with numpy's
AVX-512 arctan2, as on the machine that made the official results (`geometry.normalize_angle`).
Everything is arrays over proposals x time, for many scenes at once (`plan_references_batch`); only
the selection differs per metric version, so the versions share everything else.

Per-scene isolation: the devkit's planner keeps the tokens the ego overlaps at t0 ("collided") across
all scenes of a caching worker; here each scene starts from an empty list (see `planner_observation`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import shapely
import shapely.ops

from scorer.drivable_map import DrivableMap
from scorer.geometry import (
    EGO_HALF_LENGTH,
    EGO_HALF_WIDTH,
    EGO_LENGTH,
    EGO_WIDTH,
    BoolArray,
    FloatArray,
    IntArray,
    box_corners,
    ego_center,
    normalize_angle,
    rear_axle_round_trip,
)
from scorer.pdm_scorer import MeasureSettings, comfort_of, measure_alike, score_measures
from scorer.planner_observation import PlannerObservation, observe_for_planner, scoring_observation
from scorer.route import (
    Route,
    RouteError,
    build_road_graph,
    centerline_lanes,
    correct_route,
    discrete_centerline,
    load_route,
    starting_lane,
)
from scorer.scene import Scene
from scorer.simulation import simulate
from scorer.svml_pow import power_avx512
from scorer.trajectory import initial_state
from scorer.versions import ScorerConfig

SPEED_LIMIT_FRACTIONS = np.array([0.2, 0.4, 0.6, 0.8, 1.0])
FALLBACK_TARGET_SPEED = 15.0  # m/s, when the starting lane has no speed limit
MIN_GAP = 1.0  # m
HEADWAY_TIME = 1.5  # s
ACCEL_MAX = 1.5  # m/s^2
DECEL_MAX = 3.0  # m/s^2
ACCELERATION_EXPONENT = 10
LATERAL_OFFSETS = (-1.0, 1.0)  # m, paths 1 and 2 (path 0 is the centerline)
PROPOSAL_STEPS = 40  # proposals: 40 steps of 0.1 s
TRAJECTORY_STEPS = 50  # the cached trajectory: 50 steps of 0.1 s
STEP_S = 0.1
LEADING_AGENT_UPDATE = 2  # the leading agent is searched every 2nd step
NUM_POLICIES = len(SPEED_LIMIT_FRACTIONS)
NUM_PATHS = 1 + len(LATERAL_OFFSETS)


@dataclass(frozen=True, eq=False)
class PlannerOutput:
    """What the metric cache keeps of PDM-Closed, per metric version."""

    route_roadblocks: tuple[str, ...]  # corrected route roadblock ids
    route_lane_ids: tuple[str, ...]  # lanes and lane connectors of the corrected route
    centerline: FloatArray  # (n, 3) x, y, heading
    idm_target_velocities: FloatArray  # (5,)
    trajectory: FloatArray  # (51, 3) rear-axle poses at t0 + k * 0.1 s, as the cached EgoStates report them
    proposal: int  # index of the selected proposal (path * 5 + policy)


@dataclass(frozen=True, eq=False)
class PdmPath:
    """A discrete path interpolated over arc length (`PDMPath`)."""

    states: FloatArray  # (n, 3) x, y and the unwrapped heading
    progress: FloatArray  # (n,) cumulative arc length
    linestring: shapely.LineString

    @classmethod
    def from_poses(cls, poses: FloatArray) -> PdmPath:
        """Return the path through `poses` (n, 3)."""
        states = poses.copy()
        states[:, 2] = np.unwrap(states[:, 2], axis=0)
        steps = np.linalg.norm(
            np.concatenate([[np.diff(poses[:, 0])], [np.diff(poses[:, 1])]], axis=0), axis=0
        )
        progress = np.cumsum(np.append(0.0, steps), dtype=np.float64)
        return cls(states=states, progress=progress, linestring=shapely.linestrings(states[:, :2]))

    @property
    def length(self) -> float:
        """Return the arc length (cumulative sum, not shapely's length)."""
        return self.progress[-1]

    def substring(self, start: float, end: float) -> shapely.LineString:
        """Return the part of the path between two arc lengths: its vertices, or shapely's substring if < 2."""
        start, end = np.clip(start, 0.0, self.length), np.clip(end, 0.0, self.length)
        inside = (start <= self.progress) & (self.progress <= end)
        if inside.sum() > 1:
            return shapely.LineString(self.states[inside, :2])
        return shapely.ops.substring(self.linestring, start, end)


def interpolate_paths(
    states: FloatArray,
    progress: FloatArray,
    last_vertex: IntArray,
    distances: FloatArray,
    wrap: Callable[[FloatArray], FloatArray],
) -> FloatArray:
    """Return poses (m, t, 3) at distances (m, t) along paths (`PDMPath.interpolate`, one path per row).

    `states` (m, n, 3) and `progress` (m, n) may be padded past each path's `last_vertex` (progress
    +inf there). Distances are clipped to [1e-5, length]; scipy interp1d's linear formula over x, y and
    the unwrapped heading; the heading is then wrapped with `wrap` and NaN (zero-length segments) become 0.
    """
    path = np.arange(len(states))[:, None]
    clipped = np.clip(distances, 1e-5, progress[path, last_vertex[:, None]])
    # searchsorted (side "left") for every path at once: the count of arc lengths below the distance.
    upper = np.minimum(
        np.maximum((progress[:, None, :] < clipped[..., None]).sum(axis=-1), 1), last_vertex[:, None]
    )
    lower = upper - 1
    x_low = progress[path, lower]
    slope = (states[path, upper] - states[path, lower]) / (progress[path, upper] - x_low)[..., None]
    poses = slope * (clipped - x_low)[..., None] + states[path, lower]
    poses[..., 2] = wrap(poses[..., 2])
    poses[np.isnan(poses)] = 0.0
    return poses


def _unwrapped(heading: FloatArray) -> FloatArray:
    return heading


def parallel_poses(poses: FloatArray, offset: float) -> FloatArray:
    """Return the poses moved by `offset` to the left of their heading (negative: right)."""
    normal = poses[:, 2] + np.pi / 2
    return np.column_stack(
        [poses[:, 0] + np.cos(normal) * offset, poses[:, 1] + np.sin(normal) * offset, poses[:, 2]]
    )


def ego_polygons(poses: FloatArray) -> npt.NDArray[np.object_]:
    """Return the ego footprints (m,) of rear-axle poses (m, 3) (`CarFootprint.build_from_rear_axle`)."""
    center_x, center_y = ego_center(poses[:, 0], poses[:, 1], poses[:, 2])
    return shapely.polygons(box_corners(center_x, center_y, poses[:, 2], EGO_HALF_LENGTH, EGO_HALF_WIDTH))


def idm_step(
    progress: FloatArray, speed: FloatArray, leading: FloatArray, targets: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return progress and speed after one IDM step; `leading` (m, 3) = progress, speed, rear length."""
    lead_progress, lead_speed, lead_rear = leading[:, 0], leading[:, 1], leading[:, 2]
    desired_gap = (
        MIN_GAP + speed * HEADWAY_TIME + (speed * (speed - lead_speed)) / (2 * np.sqrt(ACCEL_MAX * DECEL_MAX))
    )
    gap = np.maximum(lead_progress - progress - lead_rear, MIN_GAP)
    acceleration = ACCEL_MAX * (
        1 - power_avx512(speed / targets, ACCELERATION_EXPONENT) - (desired_gap / gap) ** 2
    )
    acceleration = np.clip(acceleration, -DECEL_MAX, ACCEL_MAX)
    return progress + STEP_S * speed, speed + STEP_S * acceleration


def _shared_buffer(values: FloatArray, written: npt.NDArray[np.bool_], groups: IntArray) -> FloatArray:
    """Return, per row, the value last written at or before it within its group, else 0.

    The devkit fills one 3-value buffer per path and step, proposal after proposal, so a value a
    proposal does not write is the previous proposal's (docs/engine.md, "PDM-Closed: the IDM unroll").
    """
    rows = np.arange(len(values))
    last_written = np.maximum.accumulate(np.where(written, rows, -1))
    group_start = np.maximum.accumulate(np.where(np.r_[True, groups[1:] != groups[:-1]], rows, 0))
    return np.where(last_written >= group_start, values[np.maximum(last_written, 0)], 0.0)


class IdmUnroll:
    """IDM unroll of proposals along their paths (`PDMGenerator`), for many scenes at once.

    Rows are proposals (scene-major, path * 5 + policy within a scene); every step is one array pass
    over all rows, so the per-call cost of numpy (and of the AVX-512 arctan2) is paid once per batch.
    """

    def __init__(self, scenes: Sequence[ScenePlan]) -> None:
        paths = [path for plan in scenes for path in plan.paths]
        self.path_of = np.repeat(np.arange(len(paths)), NUM_POLICIES)
        self.targets = np.concatenate([np.tile(plan.targets, NUM_PATHS) for plan in scenes])
        self.last_vertex = np.array([len(path.progress) - 1 for path in paths])
        self.progress = np.full((len(paths), self.last_vertex.max() + 1), np.inf)
        self.states = np.zeros((*self.progress.shape, 3))
        for index, path in enumerate(paths):
            self.progress[index, : len(path.progress)] = path.progress
            self.states[index, : len(path.progress)] = path.states
        self.path_lengths = np.array(
            [path.linestring.length for path in paths]
        )  # shapely's, for free driving
        count = len(self.path_of)
        self.idm = np.zeros((count, TRAJECTORY_STEPS + 1, 2))  # progress, speed
        self.leading = np.zeros((count, TRAJECTORY_STEPS + 1, 3))  # progress, speed, rear length

        # Objects of all scenes side by side; per forecast map, each path's corridor contents in the devkit's
        # STRtree order without the collided objects, with their progress along the path (centroid projected).
        observations = [plan.observation for plan in scenes]
        offsets = np.cumsum([0] + [len(observation.tokens) for observation in observations])
        self.polygons = np.concatenate([observation.polygons for observation in observations], axis=1)
        self.is_agent = np.concatenate([observation.is_agent for observation in observations])
        self.is_red_light = np.concatenate([observation.is_red_light for observation in observations])
        self.speeds = np.concatenate([observation.speeds for observation in observations])
        self.headings = np.concatenate([observation.headings for observation in observations])
        self.collided = np.concatenate([observation.collided for observation in observations])
        lines = np.array([path.linestring for path in paths], dtype=object)
        rear_axles = shapely.points(np.repeat([plan.rear_axle for plan in scenes], NUM_PATHS, axis=0))
        start = shapely.line_locate_point(lines, rear_axles)  # each path's initial progress
        # The corridor: the path ahead of the initial progress over the fastest policy's 5 s, ego-wide.
        reach = (
            np.repeat([abs(np.max(plan.targets)) for plan in scenes], NUM_PATHS) * TRAJECTORY_STEPS * STEP_S
        )
        ahead = [
            path.substring(first, first + far) for path, first, far in zip(paths, start, reach, strict=True)
        ]
        corridors = shapely.buffer(np.array(ahead, dtype=object), EGO_WIDTH / 2, cap_style="square")
        # Prepared once for the 26 maps' queries (a query prepares an unprepared geometry each time).
        shapely.prepare(corridors)
        hit_map, hit_path, hit_object = [], [], []
        for index, plan in enumerate(scenes):
            own_paths = slice(index * NUM_PATHS, (index + 1) * NUM_PATHS)
            for map_index, tree in enumerate(plan.observation.trees):
                found, objects = tree.query(corridors[own_paths], predicate="intersects")
                hit_map.append(np.full(len(found), map_index))
                hit_path.append(index * NUM_PATHS + found)
                hit_object.append(offsets[index] + objects)
        self.hit_map, self.hit_path, self.hit_object = (
            np.concatenate(h) for h in (hit_map, hit_path, hit_object)
        )
        keep = ~self.collided[self.hit_object]
        self.hit_map, self.hit_path, self.hit_object = (
            self.hit_map[keep],
            self.hit_path[keep],
            self.hit_object[keep],
        )
        centroids = shapely.centroid(self.polygons[self.hit_map, self.hit_object])
        self.hit_progress = shapely.line_locate_point(lines[self.hit_path], centroids)

        self.idm[:, 0, 0] = start[self.path_of]
        self.idm[:, 0, 1] = np.repeat([plan.speed for plan in scenes], NUM_PATHS * NUM_POLICIES)

    def run(self, rows: IntArray, steps: range, groups: IntArray) -> None:
        """Advance the proposals `rows` (sorted) through time indices `steps`.

        `groups` (one per row, consecutive) are the devkit's calls that share one leading-agent buffer:
        the proposals of a path while unrolling, each proposal alone when extending the selected one.
        """
        for step in steps:
            if step % LEADING_AGENT_UPDATE:
                self.leading[rows, step] = self.leading[rows, step - 1]
            else:
                self.leading[rows, step] = self._leading_agents(rows, step, groups)
            previous = self.idm[rows, step - 1]
            self.idm[rows, step, 0], self.idm[rows, step, 1] = idm_step(
                previous[:, 0], previous[:, 1], self.leading[rows, step], self.targets[rows]
            )

    def poses(self, rows: IntArray, steps: slice, wrap: Callable[[FloatArray], FloatArray]) -> FloatArray:
        """Return the path poses (len(rows), steps, 3) at the rows' progress, headings wrapped with `wrap`."""
        paths = self.path_of[rows]
        return interpolate_paths(
            self.states[paths], self.progress[paths], self.last_vertex[paths], self.idm[rows, steps, 0], wrap
        )

    def _leading_agents(self, rows: IntArray, step: int, groups: IntArray) -> FloatArray:
        """Return the leading-agent buffer values (len(rows), 3) at an update step (`_update_leading_agents`)."""
        map_index = PlannerObservation.map_index(step)
        paths = self.path_of[rows]
        ego_progress = self.idm[rows, step - 1, 0]
        # Pairs (corridor object, row of its path), objects in corridor order; keep those ahead of the ego.
        hits = np.flatnonzero(self.hit_map == map_index)
        first_row = np.searchsorted(paths, self.hit_path[hits], side="left")
        row_count = np.searchsorted(paths, self.hit_path[hits], side="right") - first_row
        pair_hit = np.repeat(hits, row_count)
        pair_row = np.repeat(first_row - np.cumsum(row_count) + row_count, row_count) + np.arange(
            row_count.sum()
        )
        ahead = self.hit_progress[pair_hit] > ego_progress[pair_row]
        pair_hit, pair_row = pair_hit[ahead], pair_row[ahead]

        has_lead = np.bincount(pair_row, minlength=len(rows)) > 0
        lead = np.zeros(len(rows), dtype=np.intp)
        lead_distance = np.zeros(len(rows))
        lead_speed = np.zeros(len(rows))
        writes_speed = np.zeros(len(rows), dtype=bool)
        if len(pair_row):
            # Only the rows with an object ahead need the ego's pose and footprint (each row's alone).
            searching = np.flatnonzero(has_lead)
            ego = self.poses(rows[searching], slice(step - 1, step), _unwrapped)[:, 0]
            # The ego's heading wrapped once (numpy's AVX-512 arctan2, replayed without AVX-512 at a cost per
            # call): its footprint and an agent's relative heading below read the same wrap.
            ego[:, 2] = normalize_angle(ego[:, 2])
            ego_heading = np.zeros(len(rows))
            ego_heading[searching] = ego[:, 2]
            objects = self.hit_object[pair_hit]
            footprints = np.empty(len(rows), dtype=object)
            footprints[searching] = ego_polygons(ego)
            distances = shapely.distance(footprints[pair_row], self.polygons[map_index, objects])
            # Per row the nearest object, the first in corridor order on ties.
            order = np.argsort(pair_row, kind="stable")
            nearest = order[np.lexsort((distances[order], pair_row[order]))]
            first = np.r_[True, np.diff(pair_row[nearest]) != 0]
            chosen = nearest[first]
            lead[pair_row[chosen]] = objects[chosen]
            lead_distance[pair_row[chosen]] = distances[chosen]
            writes_speed = has_lead & ~self.is_red_light[lead]
            # An agent's speed projected on the ego heading (static objects stand, red lights leave the buffer
            # as is); its last bits follow the devkit's wraps, so these take numpy's AVX-512 arctan2.
            agent = has_lead & self.is_agent[lead]
            if agent.any():
                relative_heading = normalize_angle(self.headings[lead[agent]] - ego_heading[agent])
                lead_speed[agent] = self.speeds[lead[agent]] * np.cos(relative_heading)

        leading = np.empty((len(rows), 3))
        leading[:, 0] = np.where(has_lead, ego_progress + lead_distance, self.path_lengths[paths])
        leading[:, 1] = _shared_buffer(lead_speed, writes_speed, groups)
        leading[:, 2] = _shared_buffer(np.full(len(rows), EGO_LENGTH / 2), ~has_lead, groups)
        return leading


def idm_target_speeds(speed_limit_mps: float | None) -> FloatArray:
    """Return the 5 IDM target speeds: fractions of the starting lane's speed limit, or of 15 m/s without one."""
    return SPEED_LIMIT_FRACTIONS * (FALLBACK_TARGET_SPEED if speed_limit_mps is None else speed_limit_mps)


@dataclass(frozen=True, eq=False)
class ScenePlan:
    """What PDM-Closed builds for a scene before unrolling: route, centerline, paths, targets, forecast."""

    route: Route
    centerline: FloatArray  # (n, 3)
    paths: tuple[PdmPath, ...]  # the centerline and its -1 m / +1 m offsets
    targets: FloatArray  # (5,) IDM target speeds
    observation: PlannerObservation
    rear_axle: tuple[float, float]  # the initial EgoState's rear axle (after the round trip)
    speed: float  # the initial longitudinal rear-axle speed


def plan_scene(scene: Scene, drivable_map: DrivableMap) -> ScenePlan:
    """Return the corrected route, starting lane, centerline, paths, targets and forecast.

    See docs/engine.md, "PDM-Closed" and "Observation and forecasts: PDM-Closed's forecast".
    """
    ego = scene.current_frame.ego
    rear_x, rear_y = rear_axle_round_trip(ego.x, ego.y, ego.heading)
    rear_axle = (float(rear_x), float(rear_y), ego.heading)  # what EgoState.rear_axle reports
    center_x, center_y = ego_center(ego.x, ego.y, ego.heading)
    center = (float(center_x), float(center_y))
    footprint = ego_polygons(np.array([[ego.x, ego.y, ego.heading]]))[0]

    graph = build_road_graph(scene.map)
    route = load_route(graph, scene.current_frame.route_roadblocks, scene.token)
    if not route.blocks:
        raise RouteError(f"{scene.token}: the current frame has no route roadblocks")
    route = correct_route(graph, scene.map, route, rear_axle, scene.token)
    drivable_tree = shapely.STRtree(drivable_map.polygons, node_capacity=10)
    lane = starting_lane(graph, route, drivable_map, drivable_tree, rear_axle, center, footprint)
    centerline = discrete_centerline(graph, centerline_lanes(graph, route, lane))
    paths = (PdmPath.from_poses(centerline),) + tuple(
        PdmPath.from_poses(parallel_poses(centerline, offset)) for offset in LATERAL_OFFSETS
    )
    return ScenePlan(
        route=route,
        centerline=centerline,
        paths=paths,
        targets=idm_target_speeds(lane.speed_limit_mps),
        observation=observe_for_planner(scene, {lane.id: lane for lane in route.lanes}, footprint),
        rear_axle=rear_axle[:2],
        speed=ego.vx,
    )


@dataclass(frozen=True, eq=False)
class Proposals:
    """The 15 IDM proposals of each scene, unrolled over 4 s together, before selection."""

    plans: tuple[ScenePlan, ...]
    unroll: IdmUnroll

    def rows(self, scene_index: int) -> IntArray:
        """Return the rows of a scene's 15 proposals."""
        count = NUM_PATHS * NUM_POLICIES
        return np.arange(scene_index * count, (scene_index + 1) * count)

    def poses(self, rows: IntArray, steps: slice) -> FloatArray:
        """Return proposals' poses (len(rows), steps, 3) as the devkit stores them (AVX-512 heading wrap)."""
        return self.unroll.poses(rows, steps, normalize_angle)


def unroll_proposals(plans: Sequence[ScenePlan]) -> Proposals:
    """Return the scenes' 15 proposals each, unrolled over the 40 proposal steps.

    See docs/engine.md, "PDM-Closed: proposals and paths" and "PDM-Closed: the IDM unroll".
    """
    unroll = IdmUnroll(plans)
    rows = np.arange(len(unroll.path_of))
    unroll.run(rows, range(1, PROPOSAL_STEPS + 1), groups=unroll.path_of)
    return Proposals(plans=tuple(plans), unroll=unroll)


def best_proposals(
    states: FloatArray,
    plans: Sequence[ScenePlan],
    drivable_maps: Sequence[DrivableMap],
    configs: Sequence[ScorerConfig],
) -> IntArray:
    """Return the index (S, C) of each scene's best proposal under each planner config, from the simulated
    proposals (S, 15, 41, 11): the devkit's `score_proposals` per scene and config, then the first best score.

    A token's measures do not depend on the tokens measured with it, so the scenes are measured together, and
    once for all configs (`measure_alike`): only what a config's `MeasureSettings` change is measured apart.
    Likewise v1's comfort is judged once per series (`comfort_of`), which both v1 configs read.
    """
    observations = [scoring_observation(plan.observation) for plan in plans]
    inputs = (
        [observations] * len(configs),
        drivable_maps,
        [plan.centerline[:, :2] for plan in plans],
        [plan.route.lane_ids for plan in plans],
    )
    measured = measure_alike(states, *inputs, [MeasureSettings.of(config) for config in configs])
    best = np.empty((len(plans), len(configs)), dtype=np.intp)
    known: list[tuple[FloatArray, BoolArray]] = []  # v1.0's and v1.1's planners judge the same series
    for column, (config, measures) in enumerate(zip(configs, measured, strict=True)):
        comfortable = comfort_of(measures.comfort_series, known) if "comfortable" in config.weights else None
        best[:, column] = np.argmax(score_measures(measures, config, comfortable=comfortable).score, axis=1)
    return best


def plan_references_batch(
    scenes: Sequence[Scene], drivable_maps: Sequence[DrivableMap], configs: Sequence[ScorerConfig]
) -> list[list[PlannerOutput]]:
    """Return PDM-Closed's output per scene and planner scorer config, the scenes unrolled and simulated together."""
    proposals = unroll_proposals(
        [plan_scene(scene, drivable_map) for scene, drivable_map in zip(scenes, drivable_maps, strict=True)]
    )
    rows = np.arange(len(proposals.unroll.path_of))
    initial = np.repeat(
        [initial_state(scene.current_frame.ego) for scene in scenes], NUM_PATHS * NUM_POLICIES, axis=0
    )
    simulated = simulate(proposals.poses(rows, slice(0, PROPOSAL_STEPS + 1)), initial)
    count = NUM_PATHS * NUM_POLICIES
    best = best_proposals(
        simulated.reshape(len(scenes), count, *simulated.shape[1:]), proposals.plans, drivable_maps, configs
    )
    selected = best + count * np.arange(len(scenes))[:, None]
    # Only the selected proposals are unrolled on to 5 s, each alone (its own leading-agent buffer).
    extended = np.unique(selected)
    proposals.unroll.run(extended, range(PROPOSAL_STEPS + 1, TRAJECTORY_STEPS + 1), groups=extended)
    poses = dict(
        zip(extended.tolist(), proposals.poses(extended, slice(0, TRAJECTORY_STEPS + 1)), strict=True)
    )
    outputs = []
    for index, plan in enumerate(proposals.plans):
        scene_outputs = []
        for row in selected[index]:
            x, y = rear_axle_round_trip(poses[row][:, 0], poses[row][:, 1], poses[row][:, 2])
            scene_outputs.append(
                PlannerOutput(
                    route_roadblocks=plan.route.block_ids,
                    route_lane_ids=plan.route.lane_ids,
                    centerline=plan.centerline,
                    idm_target_velocities=plan.targets,
                    trajectory=np.column_stack([x, y, poses[row][:, 2]]),
                    proposal=int(row - proposals.rows(index)[0]),
                )
            )
        outputs.append(scene_outputs)
    return outputs
