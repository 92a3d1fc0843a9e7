"""The per-scene metric cache: what scoring needs from a scene, built once and kept on disk.

One `.nlc` file per (metric version, token) holds a JSON header (metadata, and the dtype, shape and
offset of each array) followed by the arrays' raw bytes: numbers only, so a cache file can never
execute code, and read in one call (npz spent more time parsing its per-array headers than scoring). A file is
reused only while its key (scene file hash, engine version, metric version) matches; otherwise it is
rebuilt. Every scene is built in isolation: PDM-Closed's collided-track list starts empty for each
scene, unlike the devkit, whose planner instance carries it across the scenes of a worker batch.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from scorer.blas import engine_provenance
from scorer.drivable_map import DrivableMap, build_drivable_map
from scorer.files import write_atomically
from scorer.geometry import FloatArray
from scorer.observation import Observation, observe_scene
from scorer.pdm_closed import plan_references_batch
from scorer.pdm_scorer import ProposalMeasures, measure_batch
from scorer.scene import EgoStatus, Scene
from scorer.simulation import simulate
from scorer.trajectory import initial_state, pdm_references
from scorer.versions import MetricVersion

_MEASURES_PREFIX = "reference_"


@dataclass(frozen=True)
class CacheKey:
    """What a cache file was built from; any change invalidates it."""

    scene_hash: str
    engine_version: str  # with the OpenBLAS kernels, which move last bits (scorer.blas.engine_provenance)
    metric_version: str


@dataclass(frozen=True, eq=False)
class MetricCache:
    """Everything the scorer needs about one token under one metric version (NAVSIM's MetricCache)."""

    token: str
    key: CacheKey
    t0_us: int
    ego: EgoStatus
    trajectory: FloatArray  # (51, 3) PDM-Closed rear-axle poses at t0 + k * 0.1 s
    centerline: FloatArray  # (n, 3)
    route_lane_ids: tuple[str, ...]
    route_roadblocks: tuple[str, ...]
    idm_target_velocities: FloatArray
    drivable_map: DrivableMap
    observation: Observation
    # The PDM-Closed proposal simulated and measured (1, 1) once: every submission is scored against it.
    reference_measures: ProposalMeasures


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
    drivable_maps = [build_drivable_map(scene) for scene in scenes]
    observations = [observe_scene(scene) for scene in scenes]
    frames = [scene.current_frame for scene in scenes]
    # One PDM-Closed unroll serves every version; only the proposal selection differs.
    plans = plan_references_batch(scenes, drivable_maps, [version.planner for version in versions])
    # Every (version, scene) reference trajectory in one simulation, version-major.
    t0_us = np.tile([frame.timestamp_us for frame in frames], len(versions))
    trajectories = np.stack([plan[column].trajectory for column in range(len(versions)) for plan in plans])
    initial = np.tile([initial_state(frame.ego) for frame in frames], (len(versions), 1))
    states = simulate(pdm_references(t0_us, trajectories), initial).reshape(
        len(versions), len(scenes), 1, -1, initial.shape[-1]
    )
    caches: list[dict[str, MetricCache]] = [{} for _ in scenes]
    for column, version in enumerate(versions):
        version_plans = [plan[column] for plan in plans]
        measures = measure_batch(
            states[column],
            observations,
            drivable_maps,
            [plan.centerline[:, :2] for plan in version_plans],
            [plan.route_lane_ids for plan in version_plans],
            version.evaluation,
        )
        for index, (scene, plan) in enumerate(zip(scenes, version_plans, strict=True)):
            caches[index][version.name] = MetricCache(
                token=scene.token,
                key=CacheKey(scene.content_hash, engine_provenance(), version.name),
                t0_us=frames[index].timestamp_us,
                ego=frames[index].ego,
                trajectory=plan.trajectory,
                centerline=plan.centerline,
                route_lane_ids=tuple(plan.route_lane_ids),
                route_roadblocks=tuple(plan.route_roadblocks),
                idm_target_velocities=np.asarray(plan.idm_target_velocities, dtype=np.float64),
                drivable_map=drivable_maps[index],
                observation=observations[index],
                reference_measures=measures.token(index),
            )
    return caches


def cache_path(cache_dir: Path, version: str, token: str) -> Path:
    """Return where the cache of `token` under `version` is stored."""
    return Path(cache_dir) / version / f"{token}.nlc"


def _pack_polygons(polygons: Iterable[shapely.Polygon]) -> tuple[FloatArray, np.ndarray]:
    """Return the exterior coordinates of polygons and each polygon's coordinate count."""
    polygons = np.asarray(list(polygons), dtype=object)
    rings = shapely.get_exterior_ring(polygons)
    return shapely.get_coordinates(rings), shapely.get_num_coordinates(rings).astype(np.int64)


def _unpack_polygons(coords: FloatArray, counts: np.ndarray) -> np.ndarray:
    """Return one single-ring polygon per count, in one call (faster than rings, then polygons)."""
    if not len(counts):
        return np.empty(0, dtype=object)
    ring_offsets = np.concatenate([[0], np.cumsum(counts)])
    polygon_offsets = np.arange(len(counts) + 1)
    return shapely.from_ragged_array(shapely.GeometryType.POLYGON, coords, (ring_offsets, polygon_offsets))


def save_cache(cache: MetricCache, cache_dir: Path) -> Path:
    """Write `cache` atomically (temporary file, then rename) and return its path."""
    observation, drivable_map = cache.observation, cache.drivable_map
    map_coords, map_counts = _pack_polygons(drivable_map.polygons)
    meta = {
        "token": cache.token,
        "key": asdict(cache.key),
        "t0_us": cache.t0_us,
        "ego": asdict(cache.ego),
        "route_lane_ids": list(cache.route_lane_ids),
        "route_roadblocks": list(cache.route_roadblocks),
        "map_tokens": list(drivable_map.tokens),
        "map_types": list(drivable_map.types),
        "object_tokens": list(observation.tokens),
        "object_types": list(observation.object_types),
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
        "object_corners": observation.corners[observation.present],
        **{
            _MEASURES_PREFIX + f.name: getattr(cache.reference_measures, f.name)
            for f in fields(ProposalMeasures)
        },
    }
    path = cache_path(cache_dir, cache.key.metric_version, cache.token)
    write_atomically(path, _pack(meta, arrays), durable=False)  # a lost cache file is rebuilt
    return path


def _pack(meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> bytes:
    """Return header length (8 bytes, little endian), JSON header, then each array's C-order bytes."""
    layout, blobs, offset = {}, [], 0
    for name, array in arrays.items():
        blob = np.ascontiguousarray(array).tobytes()
        layout[name] = [np.asarray(array).dtype.str, list(np.shape(array)), offset]
        blobs.append(blob)
        offset += len(blob)
    header = json.dumps({"meta": meta, "arrays": layout}).encode()
    return len(header).to_bytes(8, "little") + header + b"".join(blobs)


def _unpack(data: bytes | bytearray) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Invert `_pack`; raise ValueError on anything malformed."""
    size = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + size])
    body = memoryview(data)[8 + size :]
    arrays = {}
    for name, (dtype, shape, offset) in header["arrays"].items():
        dtype = np.dtype(dtype)
        if dtype.hasobject:
            raise ValueError(f"{name}: object arrays are not allowed")
        count = int(np.prod(shape))
        arrays[name] = np.frombuffer(body, dtype=dtype, count=count, offset=offset).reshape(shape)
    return header["meta"], arrays


def load_cache(cache_dir: Path, version: str, token: str, scene_hash: str) -> MetricCache | None:
    """Return the stored cache of `token`, or None when it is missing or was built from other inputs."""
    path = cache_path(cache_dir, version, token)
    try:
        meta, arrays = _unpack(bytearray(path.read_bytes()))  # writable arrays, as np.load gave
        key = CacheKey(**meta["key"])
    except (OSError, ValueError, KeyError, TypeError):
        return None  # missing, truncated or foreign: rebuild
    if key != CacheKey(scene_hash, engine_provenance(), version):
        return None
    present = arrays["object_present"]
    corners = np.full((*present.shape, 4, 2), np.nan)
    corners[present] = arrays["object_corners"]
    return MetricCache(
        token=meta["token"],
        key=key,
        t0_us=meta["t0_us"],
        ego=EgoStatus(**meta["ego"]),
        trajectory=arrays["trajectory"],
        centerline=arrays["centerline"],
        route_lane_ids=tuple(meta["route_lane_ids"]),
        route_roadblocks=tuple(meta["route_roadblocks"]),
        idm_target_velocities=arrays["idm_target_velocities"],
        drivable_map=DrivableMap(
            tokens=tuple(meta["map_tokens"]),
            types=tuple(meta["map_types"]),
            polygons=_unpack_polygons(arrays["map_coords"], arrays["map_counts"]),
        ),
        observation=Observation(
            tokens=tuple(meta["object_tokens"]),
            object_types=tuple(meta["object_types"]),
            is_agent=arrays["object_is_agent"],
            first_speed=arrays["object_first_speed"],
            present=present,
            corners=corners,
        ),
        reference_measures=ProposalMeasures(
            **{f.name: arrays[_MEASURES_PREFIX + f.name] for f in fields(ProposalMeasures)}
        ),
    )
