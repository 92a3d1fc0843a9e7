"""The per-scene metric cache: what scoring needs from a scene, built once and kept on disk.

One `.nlc` file per token holds every metric version's cache (`_pack` gives the layout): one JSON header
(the key, each distinct metadata value once, each distinct array's dtype, shape and offset, and per version
which of them it holds by name), then the arrays' raw bytes, each distinct content once, so the versions share
the map and, where they observe alike, the observation (v1.0 and v1.1's were identical). Numbers only, so a
cache file can never execute code; read in one call (npz spent more time parsing its per-array headers than
scoring), what versions share parsed and viewed once (a log-replay token's three sections cost about one).
A file is reused only while its key (scene file hash, engine version) matches;
otherwise it is rebuilt. Every scene is built in isolation: PDM-Closed's collided-track list starts empty
for each scene, unlike the devkit, whose planner instance carries it across the scenes of a worker batch.
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
import json
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import asdict, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import shapely

from scorer.blas import engine_provenance
from scorer.collector import collector_paused
from scorer.drivable_map import DrivableMap, build_drivable_map, outline_polygons, polygon_outlines
from scorer.files import write_atomically
from scorer.geometry import FloatArray
from scorer.human import FILTERED_COLUMNS, human_future_poses, is_synthetic
from scorer.json_reading import read_json
from scorer.metrics.history_comfort import past_states
from scorer.observation import Observation, drop_tracks_on_ego, observe_scene
from scorer.pdm_scorer import MeasureSettings, ProposalMeasures, measure_alike, score_batch
from scorer.red_lights import RedLights, observe_red_lights
from scorer.scene import EgoStatus, Scene
from scorer.simulation import simulate
from scorer.trajectory import agent_references, initial_state, pdm_references
from scorer.versions import VERSIONS, MetricVersion, cache_source

if TYPE_CHECKING:
    from scorer.pdm_closed import PlannerOutput
    from scorer.reactive.agents import StartingTraffic

# Reactive traffic (`scorer.reactive`) is imported where a reactive version needs it: scoring a log-replay
# version from its cache never loads it (start-up of `navsim-lb score`).

_MEASURES_PREFIX = "reference_"
_MEASURES = ProposalMeasures._fields
_PREFIX = 16  # a cache file's first bytes: its header's length and its own, 8 bytes each


class CacheKey(NamedTuple):
    """What a cache file was built from; any change invalidates it."""

    scene_hash: str
    engine_version: str  # with the OpenBLAS kernels, which move last bits (scorer.blas.engine_provenance)
    metric_version: str


class MetricCache(NamedTuple):
    """Everything the scorer needs about one token under one metric version (NAVSIM's MetricCache)."""

    token: str
    key: CacheKey
    log_name: str
    t0_us: int
    ego: EgoStatus
    trajectory: FloatArray  # (51, 3) PDM-Closed rear-axle poses at t0 + k * 0.1 s
    centerline: FloatArray  # (n, 3)
    route_lane_ids: tuple[str, ...]
    route_roadblocks: tuple[str, ...]
    idm_target_velocities: FloatArray
    drivable_map: DrivableMap
    observation: (
        Observation  # reactive traffic: without the simulated vehicles (`scorer.reactive.observation`)
    )
    # The PDM-Closed proposal simulated and measured (1, 1) once: every submission is scored against it. Under
    # reactive traffic the reference is measured against each submission's traffic: its states instead.
    reference_measures: ProposalMeasures | None
    # v2: tracks dropped for touching the ego at t = 0, and the logged human's result for the penalty filter
    # (its columns and first infraction indices; None where the version or the scene has no filter).
    dropped_tracks: tuple[str, ...] = ()
    human: dict[str, float] | None = None
    past_states: FloatArray | None = None  # v2's history comfort: the logged past (n, 11)
    reference_states: FloatArray | None = None  # reactive traffic: PDM-Closed's simulated states (41, 11)
    starting_traffic: "StartingTraffic | None" = None  # reactive traffic: the vehicles at the start


def build_caches(scene: Scene, versions: Sequence[MetricVersion]) -> dict[str, MetricCache]:
    """Return the metric cache of `scene` for each version; observation and map are shared between them."""
    return build_cache_batch([scene], versions)[0]


def build_cache_batch(
    scenes: Sequence[Scene], versions: Sequence[MetricVersion]
) -> list[dict[str, MetricCache]]:
    """Return each scene's metric cache per version, as `build_caches` gives it for the scene alone.

    The scenes share the array calls of the PDM-Closed unroll, the simulations and the measures (numpy's
    per-call cost is most of a scene's), nothing else: every scene is planned and measured on its own.
    """
    with collector_paused():  # most of what a batch allocates is short-lived and acyclic
        return _build_cache_batch(scenes, versions)


def _build_cache_batch(
    scenes: Sequence[Scene], versions: Sequence[MetricVersion]
) -> list[dict[str, MetricCache]]:
    # PDM-Closed is imported where a cache is built: scoring from a warm cache never plans (3 ms of start-up).
    from scorer.pdm_closed import plan_references_batch

    drivable_maps = [build_drivable_map(scene) for scene in scenes]
    frames = [scene.current_frame for scene in scenes]
    # One PDM-Closed unroll serves every version; only the proposal selection differs.
    plans = plan_references_batch(scenes, drivable_maps, [version.planner for version in versions])
    t0_us = np.array([frame.timestamp_us for frame in frames])
    trajectories = np.stack([plan[column].trajectory for column in range(len(versions)) for plan in plans])
    initial = np.stack([initial_state(frame.ego) for frame in frames])
    # The logged humans of original scenes, for the versions with the penalty filter (`score_humans`).
    humans: list[int] = []
    if any(version.human_penalty_filter for version in versions):
        humans = [index for index, scene in enumerate(scenes) if not is_synthetic(scene.token)]
    references = [pdm_references(np.tile(t0_us, len(versions)), trajectories)]
    if humans:
        poses = np.stack([human_future_poses(scenes[index]) for index in humans])
        references.append(agent_references(initial[humans], t0_us[humans], poses))
    # Every (version, scene) reference trajectory, version-major, then the humans, in one simulation: rows
    # are independent, and each simulate call pays numpy's per-call cost 40 steps over.
    simulated = simulate(
        np.concatenate(references), np.concatenate([np.tile(initial, (len(versions), 1)), initial[humans]])
    )
    count = len(versions) * len(scenes)
    states = simulated[:count].reshape(len(versions), len(scenes), 1, -1, initial.shape[-1])
    keys = [observation_key(version) for version in versions]
    # Versions that observe alike share the observation.
    observed = {key: [evaluation_observation(scene, *key) for scene in scenes] for key in dict.fromkeys(keys)}
    observations = [[observation for observation, _ in observed[key]] for key in keys]
    reference_measures = _reference_measures(states, versions, observations, drivable_maps, plans)
    caches: list[dict[str, MetricCache]] = [{} for _ in scenes]
    for column, version in enumerate(versions):
        version_plans = [plan[column] for plan in plans]
        inputs = (
            observations[column],
            drivable_maps,
            [plan.centerline[:, :2] for plan in version_plans],
            [plan.route_lane_ids for plan in version_plans],
        )
        pasts = None
        if "history_comfort" in version.evaluation.weights:
            pasts = [past_states(scene) for scene in scenes]
        traffic: list[StartingTraffic | None] = [None] * len(scenes)
        if version.reactive_traffic is not None:
            from scorer.reactive.agents import build_agents

            traffic = [
                build_agents(
                    scene.current_frame, scene.map, _initial_ego_box(scene), version.reactive_traffic
                )
                for scene in scenes
            ]
        human_results: list[dict[str, float] | None] = [None] * len(scenes)
        if version.human_penalty_filter:
            human_observations = _human_observations(
                humans, simulated[count:], observations[column], traffic, version
            )
            human_results = score_humans(
                humans, simulated[count:], len(scenes), human_observations, *inputs[1:], version
            )
        for index, (scene, plan) in enumerate(zip(scenes, version_plans, strict=True)):
            caches[index][version.name] = MetricCache(
                token=scene.token,
                key=CacheKey(scene.content_hash, engine_provenance(), version.name),
                log_name=scene.log_name,
                t0_us=frames[index].timestamp_us,
                ego=frames[index].ego,
                trajectory=plan.trajectory,
                centerline=plan.centerline,
                route_lane_ids=tuple(plan.route_lane_ids),
                route_roadblocks=tuple(plan.route_roadblocks),
                idm_target_velocities=np.asarray(plan.idm_target_velocities, dtype=np.float64),
                drivable_map=drivable_maps[index],
                observation=observations[column][index],
                reference_measures=reference_measures[column][index],
                dropped_tracks=observed[keys[column]][index][1],
                human=human_results[index],
                past_states=None if pasts is None else pasts[index],
                reference_states=None if traffic[index] is None else states[column, index, 0],
                starting_traffic=traffic[index],
            )
    return caches


def _human_observations(
    humans: Sequence[int],
    states: FloatArray,
    observations: Sequence[Observation],
    traffic: "Sequence[StartingTraffic | None]",
    version: MetricVersion,
) -> list[Observation]:
    """Return what the logged human of each scene is scored against: under reactive traffic, a second
    simulation whose vehicles react to the human's simulated states (H, 41, 11), else the observation (also
    where the traffic could not be built: the scene's tokens are unscorable)."""
    from scorer.reactive.observation import reacting_observation

    seen = list(observations)
    for row, index in enumerate(humans):
        scene_traffic = traffic[index]
        if (
            scene_traffic is not None
            and scene_traffic.failure is None
            and version.reactive_traffic is not None
        ):
            seen[index] = reacting_observation(
                scene_traffic, seen[index], states[row], version.reactive_traffic
            )
    return seen


ObservationKey = tuple[int, bool, bool, bool]


def observation_key(version: MetricVersion) -> ObservationKey:
    """Return how a version observes a scene: future frames, red lights read, tracks on the ego dropped,
    reactive traffic."""
    reads_lights = "traffic_light_compliance" in version.evaluation.multiplier_rows
    reactive = version.reactive_traffic is not None
    return version.observation_frames, reads_lights, version.drops_tracks_on_ego, reactive


def _reference_measures(
    states: FloatArray,
    versions: Sequence[MetricVersion],
    observations: Sequence[Sequence[Observation]],
    drivable_maps: Sequence[DrivableMap],
    plans: "Sequence[Sequence[PlannerOutput]]",
) -> list[list[ProposalMeasures | None]]:
    """Return each version's measures (1, 1) of each scene's simulated reference (V, S, 1, 41, 11); None under
    reactive traffic, whose vehicles react to each submission.

    A token's measures read its own inputs only, so every version is measured in one call (`measure_alike`:
    what reads the ego and the map alone is measured once, what reads an observation once per observation),
    and a scene's reference the versions share (the same proposal selected, the same centerline and route) is
    one token.
    """
    measures: list[list[ProposalMeasures | None]] = [[None] * len(plans) for _ in versions]
    columns = [column for column, version in enumerate(versions) if version.reactive_traffic is None]
    token_of: dict[tuple[int, bytes, bytes, tuple[str, ...]], int] = {}  # a scene's inputs -> token
    tokens: list[tuple[int, int]] = []  # (column, scene) measured
    token: dict[tuple[int, int], int] = {}
    for column in columns:
        for index, scene_plans in enumerate(plans):
            plan = scene_plans[column]
            inputs = (index, states[column, index].tobytes(), plan.centerline.tobytes(), plan.route_lane_ids)
            if inputs not in token_of:
                token_of[inputs] = len(tokens)
                tokens.append((column, index))
            token[column, index] = token_of[inputs]
    if not tokens:
        return measures
    measured = measure_alike(
        np.stack([states[column, index] for column, index in tokens]),
        [[observations[column][index] for _, index in tokens] for column in columns],
        [drivable_maps[index] for _, index in tokens],
        [plans[index][column].centerline[:, :2] for column, index in tokens],
        [plans[index][column].route_lane_ids for column, index in tokens],
        [MeasureSettings.of(versions[column].evaluation) for column in columns],
    )
    for column, version_measures in zip(columns, measured, strict=True):
        measures[column] = [version_measures.token(token[column, index]) for index in range(len(plans))]
    return measures


def evaluation_observation(
    scene: Scene, future_frames: int, reads_lights: bool, drops_tracks_on_ego: bool, reactive: bool
) -> tuple[Observation, tuple[str, ...]]:
    """Return a version's evaluation observation of `scene` and the tracks it dropped for touching the ego;
    under reactive traffic, the observation without its simulated vehicles."""
    observation = observe_scene(scene, future_frames)
    if reads_lights:
        observation = replace(observation, red_lights=observe_red_lights(scene, future_frames))
    if reactive:
        from scorer.reactive.observation import base_observation

        return base_observation(scene.current_frame, observation), ()
    if not drops_tracks_on_ego:
        return observation, ()
    return drop_tracks_on_ego(observation, _initial_ego_box(scene))


def _initial_ego_box(scene: Scene) -> shapely.Polygon:
    """Return the ego's true box at the current frame."""
    from scorer.pdm_closed import ego_polygons  # see build_cache_batch

    ego = scene.current_frame.ego
    return ego_polygons(np.array([[ego.x, ego.y, ego.heading]]))[0]


def score_humans(
    original: Sequence[int],
    states: FloatArray,
    num_scenes: int,
    observations: Sequence[Observation],
    drivable_maps: Sequence[DrivableMap],
    centerlines: Sequence[FloatArray],
    route_lane_ids: Sequence[Sequence[str]],
    version: MetricVersion,
) -> list[dict[str, float] | None]:
    """Return the logged human's result per scene, as the filter reads it (None on synthetic scenes), from the
    simulated states (H, 41, 11) of the humans of the scenes `original` (`human_future_poses`).

    Each human is scored alone, a batch of one in the devkit, without past states.
    """
    humans: list[dict[str, float] | None] = [None] * num_scenes
    if not original:
        return humans
    scores = score_batch(
        states[:, None],
        [observations[index] for index in original],
        [drivable_maps[index] for index in original],
        [centerlines[index] for index in original],
        [route_lane_ids[index] for index in original],
        version.evaluation,
    )
    for row, index in enumerate(original):
        human = {column: float(getattr(scores, column)[row, 0]) for column in FILTERED_COLUMNS}
        human |= {
            name: float(getattr(scores, name)[row, 0])
            for name in (
                "progress_raw",
                "collision_index",
                "ttc_index",
                "red_light_index",
                "lane_keeping_index",
            )
        }
        humans[index] = human
    return humans


def cache_path(cache_dir: Path, token: str) -> Path:
    """Return where the caches of `token`, every version's, are stored."""
    return Path(cache_dir) / f"{token}.nlc"


def save_caches(caches: Mapping[str, MetricCache], cache_dir: Path) -> Path:
    """Write the caches of one token (by version) atomically (temporary file, then rename), beside the versions
    its file already holds for the same scene and engine, and return the file's path.

    The file is not read when `caches` holds every version: a file under the same key, written by this
    engine, holds no other (a stale cache rebuilt whole, the common case, reads nothing)."""
    first = next(iter(caches.values()))
    path = cache_path(cache_dir, first.token)
    key = {"scene_hash": first.key.scene_hash, "engine_version": first.key.engine_version}
    sections = {} if VERSIONS.keys() <= caches.keys() else _read_sections(path, key)
    shared: SharedParts = {}
    sections |= {version: _cache_section(cache, shared) for version, cache in caches.items()}
    write_atomically(path, _pack(key, sections), durable=False)  # a lost cache file is rebuilt
    return path


def _read_sections(
    path: Path, key: dict[str, str]
) -> dict[str, tuple[dict[str, Any], dict[str, np.ndarray]]]:
    """Return the versions a cache file holds under `key`: none when it is missing, damaged or from other
    inputs."""
    try:
        stored_key, sections = _unpack(path.read_bytes())
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    if stored_key != key:
        return {}
    return sections


SharedParts = dict[tuple[str, int], Any]  # a token's section parts, by kind and the id of their source


def _cache_section(cache: MetricCache, shared: SharedParts) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Return one version's metadata and arrays, as its section of a cache file holds them. What the token's
    other sections hold alike (the same map, observation, ego and route objects) is built once, from `shared`,
    and is then the same objects, which `_pack` stores by identity without encoding or hashing them again."""

    def once(kind: str, source: object, build: Callable[[], Any]) -> Any:
        key = (kind, id(source))  # the source outlives `shared`: the caches hold it
        if key not in shared:
            shared[key] = build()
        return shared[key]

    def listed(values: Sequence[Any]) -> list[Any]:
        return once("list", values, lambda: list(values))

    observation, drivable_map = cache.observation, cache.drivable_map
    map_coords, map_counts = drivable_map.outlines
    red_lights = observation.red_lights
    meta = {
        "token": cache.token,
        "log_name": cache.log_name,
        "t0_us": cache.t0_us,
        "ego": once("ego", cache.ego, cache.ego._asdict),
        "route_lane_ids": listed(cache.route_lane_ids),
        "route_roadblocks": listed(cache.route_roadblocks),
        "map_tokens": listed(drivable_map.tokens),
        "map_types": listed(drivable_map.types),
        "object_tokens": listed(observation.tokens),
        "object_types": listed(observation.object_types),
        "red_light_lanes": None if red_lights is None else listed(red_lights.lane_ids),
        "dropped_tracks": listed(cache.dropped_tracks),
        "human": cache.human,
    }
    arrays = {
        "trajectory": cache.trajectory,
        "centerline": cache.centerline,
        "idm_target_velocities": cache.idm_target_velocities,
        "map_coords": map_coords,
        "map_counts": map_counts,
        "object_present": observation.present,
        "object_is_agent": observation.is_agent,
        "object_first_speed": observation.first_speed,
        "object_corners": observation.boxes,
        **once("red_lights", red_lights, lambda: _red_light_arrays(red_lights)),
        **({} if cache.past_states is None else {"past_states": cache.past_states}),
        **({} if cache.reference_states is None else {"reference_states": cache.reference_states}),
        **(
            {}
            if cache.reference_measures is None
            else {_MEASURES_PREFIX + name: getattr(cache.reference_measures, name) for name in _MEASURES}
        ),
    }
    if cache.starting_traffic is not None:  # its JSON's bytes: parsed only where a reactive version reads it
        traffic = json.dumps(_traffic_meta(cache.starting_traffic)).encode()
        arrays["starting_traffic"] = np.frombuffer(traffic, dtype=np.uint8)
    return meta, arrays


def _traffic_meta(traffic: "StartingTraffic") -> dict[str, Any]:
    """Return the vehicles at the start as JSON (floats round-trip exactly through their shortest repr)."""
    from scorer.reactive.agents import IdmVehicle

    return {
        "agents": [
            {
                **{f.name: getattr(agent, f.name) for f in fields(IdmVehicle) if f.name != "path"},
                "path": {
                    "progress": agent.path.progress,
                    "points": agent.path.points.tolist(),
                    "unwrapped_heading": agent.path.unwrapped_heading,
                },
            }
            for agent in traffic.agents
        ],
        "rejected": {track: asdict(rejection) for track, rejection in traffic.rejected.items()},
        "parking": [asdict(candidate) for candidate in traffic.parking],
        "failure": traffic.failure,
    }


def _traffic_of(meta: dict[str, Any]) -> "StartingTraffic":
    """Invert `_traffic_meta`."""
    from scorer.reactive.agents import IdmVehicle, ParkingCandidate, Rejection, StartingTraffic
    from scorer.reactive.paths import LanePath

    agents = []
    for agent in meta["agents"]:
        path = agent["path"]
        agents.append(
            IdmVehicle(
                **{key: value for key, value in agent.items() if key not in ("path", "pose")},
                pose=tuple(agent["pose"]),
                path=LanePath(
                    progress=tuple(path["progress"]),
                    points=np.array(path["points"], dtype=np.float64),
                    unwrapped_heading=tuple(path["unwrapped_heading"]),
                ),
            )
        )
    return StartingTraffic(
        agents=tuple(agents),
        rejected={track: Rejection(**rejection) for track, rejection in meta["rejected"].items()},
        parking=tuple(ParkingCandidate(c["track"], tuple(c["box"])) for c in meta["parking"]),
        failure=meta["failure"],
    )


def _red_light_arrays(red_lights: RedLights | None) -> dict[str, np.ndarray]:
    if red_lights is None:
        return {}
    coords, counts = polygon_outlines(red_lights.polygons)
    return {"red_light_coords": coords, "red_light_counts": counts, "red_light_present": red_lights.present}


def _pack(key: dict[str, str], sections: Mapping[str, tuple[dict[str, Any], dict[str, np.ndarray]]]) -> bytes:
    """Return a cache file: the header's length and the file's (8 bytes each, little endian), the header (JSON),
    then the arrays' C-order bytes.

    The header holds the key, each distinct metadata value once (`values`), each distinct array once (`arrays`:
    dtype, shape, offset) and, per version, the index of each of its metadata values and arrays by name: the
    versions' sections hold mostly the same map, route and objects, which a reader parses and views once. An
    array's bytes are stored once, and not at all where they begin a stored array's (a shorter observation's
    corners are the first rows of a longer one's)."""
    values: list[Any] = []
    value_at: dict[str, int] = {}
    layout: list[tuple[str, tuple[int, ...], int]] = []
    array_at: dict[tuple[str, tuple[int, ...], int], int] = {}
    blobs: list[bytes] = []
    blob_at: dict[bytes, int] = {}
    size = 0
    # A value or array that several sections hold as the same object is encoded once (`_cache_section`).
    value_of_object: dict[int, int] = {}
    array_of_object: dict[int, int] = {}
    versions = {}
    for version, (meta, arrays) in sections.items():
        meta_refs = {}
        for name, value in meta.items():
            if id(value) not in value_of_object:
                text = json.dumps(value)
                if text not in value_at:
                    value_at[text] = len(values)
                    values.append(value)
                value_of_object[id(value)] = value_at[text]
            meta_refs[name] = value_of_object[id(value)]
        array_refs = {}
        for name, array in arrays.items():
            if id(array) not in array_of_object:
                blob = np.ascontiguousarray(array).tobytes()
                if blob not in blob_at:
                    within = next((at for stored, at in blob_at.items() if stored.startswith(blob)), None)
                    if within is None:
                        within, size = size, size + len(blob)
                        blobs.append(blob)
                    blob_at[blob] = within
                entry = (np.asarray(array).dtype.str, tuple(np.shape(array)), blob_at[blob])
                if entry not in array_at:
                    array_at[entry] = len(layout)
                    layout.append(entry)
                array_of_object[id(array)] = array_at[entry]
            array_refs[name] = array_of_object[id(array)]
        versions[version] = {"meta": meta_refs, "arrays": array_refs}
    header = json.dumps({"key": key, "values": values, "arrays": layout, "versions": versions}).encode()
    file_size = _PREFIX + len(header) + size
    prefix = len(header).to_bytes(8, "little") + file_size.to_bytes(8, "little")
    return prefix + header + b"".join(blobs)


def _header(data: bytes) -> tuple[dict[str, Any], int]:
    """Return a cache file's header and where its arrays' bytes start; raise ValueError if the file is not the
    size its prefix states (cut short)."""
    length, stated = int.from_bytes(data[:8], "little"), int.from_bytes(data[8:_PREFIX], "little")
    if stated != len(data):
        raise ValueError(f"a cache file of {stated} bytes holds {len(data)}")
    return read_json(data[_PREFIX : _PREFIX + length]), _PREFIX + length


Section = tuple[dict[str, Any], dict[str, np.ndarray]]  # metadata, arrays


def _unpack(
    data: bytes, versions: Collection[str] | None = None
) -> tuple[dict[str, str], dict[str, Section]]:
    """Invert `_pack` for `versions` (all by default): the file's key and each version's section, its arrays
    read-only views of `data`. What versions share on disk they share in memory: the same value and array
    objects (nothing writes a cache's metadata or arrays). Raise ValueError on anything malformed, a file cut
    short included."""
    header, body_start = _header(data)
    body = memoryview(data)[body_start:]
    values, layout = header["values"], header["arrays"]
    refs = {
        version: version_refs
        for version, version_refs in header["versions"].items()
        if versions is None or version in versions
    }
    views = {}
    for at in {at for version_refs in refs.values() for at in version_refs["arrays"].values()}:
        dtype_str, shape, offset = layout[at]
        dtype = np.dtype(dtype_str)
        if dtype.hasobject:
            raise ValueError("object arrays are not allowed")
        # The array constructor takes a view in one call, a third of `frombuffer` and `reshape`'s time; it
        # rejects negative and non-integer dimensions and a view past the end (TypeError), not a negative
        # offset, which would read before the arrays' bytes.
        if offset < 0:
            raise ValueError(f"an array at offset {offset}")
        views[at] = np.ndarray(shape, dtype, body, offset)
    sections = {
        version: (
            {name: values[at] for name, at in version_refs["meta"].items()},
            {name: views[at] for name, at in version_refs["arrays"].items()},
        )
        for version, version_refs in refs.items()
    }
    return header["key"], sections


def load_caches(
    cache_dir: Path, versions: Collection[str], token: str, scene_hash: str, data: bytes | None = None
) -> dict[str, MetricCache]:
    """Return the stored caches of `token` under `versions`, by version; a version is missing when its cache is
    missing, damaged or was built from other inputs. The versions share their map's polygons; a version that
    shares another's cache (`cache_source`) reads that version's section. `data`: the cache file's bytes when
    the caller holds them (fetched from an object store), read instead of the file."""
    key = {"scene_hash": scene_hash, "engine_version": engine_provenance()}
    sources = {version: cache_source(version) for version in versions}
    try:
        if data is None:
            data = cache_path(cache_dir, token).read_bytes()
        stored_key, sections = _unpack(data, set(sources.values()))
    except (OSError, ValueError, KeyError, TypeError):
        return {}  # missing, truncated or foreign: rebuild
    if stored_key != key:
        return {}
    shared: dict[tuple[object, ...], Any] = {}  # what sections hold alike, built once (`_cache_of`)
    of_source: dict[str, MetricCache] = {}  # a section serves every version that reads it
    caches = {}
    for version, source in sources.items():
        if source not in sections:
            continue
        version_key = CacheKey(scene_hash, key["engine_version"], version)
        if source in of_source:
            caches[version] = of_source[source]._replace(key=version_key)
            continue
        meta, arrays = sections[source]
        try:
            caches[version] = of_source[source] = _cache_of(version_key, meta, arrays, shared)
        except (ValueError, KeyError, TypeError):
            continue  # a damaged section: that version is rebuilt
    return caches


def cache_file_key(data: bytes) -> CacheKey | None:
    """Return what a cache file's bytes were built from (its metric_version left empty: a file holds every
    version it was built for), or None when they are not a whole cache file. Lets caches travel between
    machines (an object store) named by their key, without reading their arrays."""
    try:
        key = _header(data)[0]["key"]
        return CacheKey(key["scene_hash"], key["engine_version"], "")
    except (ValueError, KeyError, TypeError):
        return None


def load_cache(cache_dir: Path, version: str, token: str, scene_hash: str) -> MetricCache | None:
    """Return the stored cache of `token` under `version` (`load_caches`), or None."""
    return load_caches(cache_dir, [version], token, scene_hash).get(version)


def _cache_of(
    key: CacheKey,
    meta: dict[str, Any],
    arrays: dict[str, np.ndarray],
    shared: dict[tuple[object, ...], Any],
) -> MetricCache:
    """Return the cache a file's section holds. `shared` keeps what the file's other sections hold alike (the
    same arrays on disk, the same metadata): their map and, where they observe alike, their observation are
    built once and are the same objects."""

    def once(names: Sequence[str], metas: Sequence[str], build: Callable[[], Any]) -> Any:
        # The arrays by identity: `_unpack` gives one view per stored array (offset, dtype and shape).
        where = (*names, *metas, *(id(arrays[name]) for name in names), *(id(meta[name]) for name in metas))
        if where not in shared:
            shared[where] = build()
        return shared[where]

    def observation() -> Observation:
        red_lights = None
        if meta["red_light_lanes"] is not None:
            red_lights = RedLights(
                lane_ids=tuple(meta["red_light_lanes"]),
                polygons=outline_polygons((arrays["red_light_coords"], arrays["red_light_counts"])),
                present=arrays["red_light_present"],
            )
        return Observation(
            tokens=tuple(meta["object_tokens"]),
            object_types=tuple(meta["object_types"]),
            is_agent=arrays["object_is_agent"],
            first_speed=arrays["object_first_speed"],
            present=arrays["object_present"],
            boxes=arrays["object_corners"],
            red_lights=red_lights,
        )

    lights = (
        ("red_light_coords", "red_light_counts", "red_light_present") if "red_light_coords" in arrays else ()
    )
    object_arrays = ("object_present", "object_corners", "object_is_agent", "object_first_speed", *lights)
    object_meta = ("object_tokens", "object_types", "red_light_lanes")
    return MetricCache(
        token=meta["token"],
        key=key,
        log_name=meta["log_name"],
        t0_us=meta["t0_us"],
        ego=EgoStatus(**meta["ego"]),
        trajectory=arrays["trajectory"],
        centerline=arrays["centerline"],
        route_lane_ids=tuple(meta["route_lane_ids"]),
        route_roadblocks=tuple(meta["route_roadblocks"]),
        idm_target_velocities=arrays["idm_target_velocities"],
        drivable_map=once(
            ("map_coords", "map_counts"),
            ("map_tokens", "map_types"),
            lambda: DrivableMap(
                tokens=tuple(meta["map_tokens"]),
                types=tuple(meta["map_types"]),
                stored=(arrays["map_coords"], arrays["map_counts"]),
            ),
        ),
        observation=once(object_arrays, object_meta, observation),
        reference_measures=(
            ProposalMeasures(**{name: arrays[_MEASURES_PREFIX + name] for name in _MEASURES})
            if "starting_traffic" not in arrays
            else None
        ),
        dropped_tracks=tuple(meta["dropped_tracks"]),
        human=meta["human"],
        past_states=arrays.get("past_states"),
        reference_states=arrays.get("reference_states"),
        starting_traffic=(
            _traffic_of(read_json(arrays["starting_traffic"].tobytes()))
            if "starting_traffic" in arrays
            else None
        ),
    )
