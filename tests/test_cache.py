"""The metric cache: scenes built together as alone, a failing scene isolated, the file's exact round trip,
rebuilt when its key changes or the file is damaged."""

from __future__ import annotations

import json
from dataclasses import fields
from itertools import islice
from pathlib import Path

import numpy as np
import pytest
import shapely

from scorer import cache as scorer_cache
from scorer import evaluate
from scorer.cache import (
    MetricCache,
    build_cache_batch,
    build_caches,
    cache_path,
    load_cache,
    load_caches,
    save_caches,
)
from scorer.evaluate import score_tokens
from scorer.pdm_scorer import ProposalMeasures
from scorer.reactive.agents import IdmVehicle, StartingTraffic
from scorer.scene import Scene, iter_scenes, scene_file_hash, scene_paths
from scorer.versions import VERSIONS, MetricVersion

REFERENCE = Path(__file__).parent / "fixtures" / "reference"


@pytest.fixture(scope="module")
def built() -> tuple[str, dict[str, MetricCache]]:
    scene = next(iter_scenes(REFERENCE))
    return scene.token, build_caches(scene, list(VERSIONS.values()))


def assert_same_cache(loaded: MetricCache, cache: MetricCache) -> None:
    """Every field of two caches equal, bit for bit."""
    assert loaded.key == cache.key and loaded.ego == cache.ego and loaded.t0_us == cache.t0_us
    for name in ("trajectory", "centerline", "idm_target_velocities"):
        assert np.array_equal(getattr(loaded, name), getattr(cache, name)), name
    assert loaded.route_lane_ids == cache.route_lane_ids
    assert loaded.route_roadblocks == cache.route_roadblocks
    assert loaded.drivable_map.tokens == cache.drivable_map.tokens
    assert shapely.equals_exact(loaded.drivable_map.polygons, cache.drivable_map.polygons, 0.0).all()
    assert loaded.observation.tokens == cache.observation.tokens
    assert np.array_equal(loaded.observation.present, cache.observation.present)
    assert loaded.observation.boxes.tobytes() == cache.observation.boxes.tobytes()  # NaN and -0.0 too
    assert loaded.observation.corners.tobytes() == cache.observation.corners.tobytes()
    assert (loaded.reference_measures is None) == (cache.reference_measures is None)
    for name in ProposalMeasures._fields if cache.reference_measures is not None else ():
        assert np.array_equal(
            getattr(loaded.reference_measures, name), getattr(cache.reference_measures, name)
        ), name
    assert (loaded.reference_states is None) == (cache.reference_states is None)
    if cache.reference_states is not None:
        assert np.array_equal(loaded.reference_states, cache.reference_states)
    assert (loaded.starting_traffic is None) == (cache.starting_traffic is None)
    if loaded.starting_traffic is not None and cache.starting_traffic is not None:
        assert_same_traffic(loaded.starting_traffic, cache.starting_traffic)


def assert_same_traffic(loaded: StartingTraffic, traffic: StartingTraffic) -> None:
    """Reactive traffic at the start, every vehicle and path bit for bit."""
    assert loaded.rejected == traffic.rejected and loaded.parking == traffic.parking
    assert len(loaded.agents) == len(traffic.agents)
    for loaded_agent, agent in zip(loaded.agents, traffic.agents, strict=True):
        for field in fields(IdmVehicle):
            if field.name != "path":
                assert getattr(loaded_agent, field.name) == getattr(agent, field.name), field.name
        assert loaded_agent.path.progress == agent.path.progress
        assert loaded_agent.path.unwrapped_heading == agent.path.unwrapped_heading
        assert np.array_equal(loaded_agent.path.points, agent.path.points)


def test_round_trip_is_exact(tmp_path: Path, built: tuple[str, dict[str, MetricCache]]) -> None:
    """Versions saved one at a time join the token's file: each reads back exact, the earlier ones kept."""
    token, caches = built
    path = scene_paths(REFERENCE)[token]
    for version, cache in caches.items():
        save_caches({version: cache}, tmp_path)
        loaded = load_cache(tmp_path, version, token, scene_file_hash(path))
        assert loaded is not None
        assert_same_cache(loaded, cache)
    together = load_caches(tmp_path, list(caches), token, scene_file_hash(path))
    for version, cache in caches.items():
        assert_same_cache(together[version], cache)


def test_a_cache_file_held_in_memory_is_read_instead_of_the_directory(
    tmp_path: Path, built: tuple[str, dict[str, MetricCache]]
) -> None:
    """Caches fetched from a store reach scoring as bytes (`SceneFiles.caches`): read as the file would be,
    with nothing built or written where the directory lacks them, the rows those of the file's."""
    token, caches = built
    data = save_caches(caches, tmp_path / "disk").read_bytes()
    scene_hash = scene_file_hash(scene_paths(REFERENCE)[token])
    from_memory = load_caches(tmp_path / "empty", list(caches), token, scene_hash, data)
    for version, cache in caches.items():
        assert_same_cache(from_memory[version], cache)
    empty, paths = tmp_path / "empty", scene_paths(REFERENCE)
    poses = {token: np.column_stack([np.arange(1.0, 9.0), np.zeros(8), np.zeros(8)])}
    held = evaluate.SceneFiles(paths, caches={token: data})
    rows = evaluate.score_seeds(REFERENCE, empty, {0: poses}, list(caches), [token], scenes=held)
    assert not empty.exists()  # nothing built: the cache came from memory
    on_disk = evaluate.score_seeds(REFERENCE, tmp_path / "disk", {0: poses}, list(caches), [token])
    assert repr(rows) == repr(on_disk)  # NaN (an undefined EC) too


def test_a_file_is_read_before_it_is_written_only_to_keep_versions_not_rewritten(
    tmp_path: Path, built: tuple[str, dict[str, MetricCache]], monkeypatch: pytest.MonkeyPatch
) -> None:
    token, caches = built
    reads: list[Path] = []
    read_sections = scorer_cache._read_sections
    monkeypatch.setattr(
        scorer_cache, "_read_sections", lambda path, key: reads.append(path) or read_sections(path, key)
    )
    save_caches(caches, tmp_path)  # every version: the file's old content cannot survive
    assert reads == [] and set(caches) == set(VERSIONS)
    save_caches({"v1.1": caches["v1.1"]}, tmp_path)  # the other versions are kept
    assert reads == [cache_path(tmp_path, token)]
    path = scene_paths(REFERENCE)[token]
    assert set(load_caches(tmp_path, list(caches), token, scene_file_hash(path))) == set(caches)


def test_the_versions_share_what_they_share_on_disk(
    tmp_path: Path, built: tuple[str, dict[str, MetricCache]]
) -> None:
    """v1.0 and v1.1 observe alike: their observation and every version's map are stored once, and read back
    as one set of map polygons."""
    token, caches = built
    alone = {}
    for version, cache in caches.items():
        alone[version] = save_caches({version: cache}, tmp_path / version).stat().st_size
    together = save_caches(caches, tmp_path / "all").stat().st_size
    assert together < sum(alone.values()) - alone["v1.0"] * 0.9
    loaded = load_caches(
        tmp_path / "all", list(caches), token, scene_file_hash(scene_paths(REFERENCE)[token])
    )
    assert len({id(cache.drivable_map.polygons) for cache in loaded.values()}) == 1
    assert not loaded["v1.1"].observation.present.flags.writeable  # shared bytes: nothing may write them


def test_what_the_versions_share_as_objects_is_written_as_if_each_had_its_own(
    built: tuple[str, dict[str, MetricCache]],
) -> None:
    """A file's bytes depend on its sections' contents alone, not on which objects the versions share."""
    _, caches = built
    key = {"scene_hash": "hash", "engine_version": "engine"}
    shared: scorer_cache.SharedParts = {}
    sections = {version: scorer_cache._cache_section(cache, shared) for version, cache in caches.items()}
    copies = {
        version: (json.loads(json.dumps(meta)), {name: np.copy(array) for name, array in arrays.items()})
        for version, (meta, arrays) in sections.items()
    }
    assert sections["v1.0"][1]["map_coords"] is sections["v1.1"][1]["map_coords"]
    data = scorer_cache._pack(key, sections)
    assert data == scorer_cache._pack(key, copies)
    for version, (meta, arrays) in scorer_cache._unpack(data)[1].items():
        assert json.dumps(meta) == json.dumps(copies[version][0])
        assert arrays.keys() == copies[version][1].keys()
        for name, array in arrays.items():
            copy = copies[version][1][name]
            assert (array.dtype, array.shape, array.tobytes()) == (copy.dtype, copy.shape, copy.tobytes())


def test_scenes_built_together_get_the_caches_each_gets_alone() -> None:
    versions = list(VERSIONS.values())
    scenes = list(islice(iter_scenes(REFERENCE), 12))
    together = build_cache_batch(scenes, versions)
    for scene, caches in zip(scenes, together, strict=True):
        alone = build_caches(scene, versions)
        for version in VERSIONS:
            assert caches[version].token == scene.token
            assert_same_cache(caches[version], alone[version])


def test_a_scene_that_breaks_its_batch_fails_alone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    paths = list(scene_paths(REFERENCE).values())[:5]
    broken = paths[2].name.split(".")[0]

    def build_unless_broken(
        scenes: list[Scene], versions: list[MetricVersion]
    ) -> list[dict[str, MetricCache]]:
        if any(scene.token == broken for scene in scenes):
            raise RuntimeError("engine bug")
        return build_cache_batch(scenes, versions)

    monkeypatch.setattr(evaluate, "build_cache_batch", build_unless_broken)
    built, errors = evaluate.build_missing_caches(paths, tmp_path, list(VERSIONS))
    assert set(errors) == {paths[2].name} and isinstance(errors[paths[2].name], RuntimeError)
    assert set(built) == {path.name for path in paths} - {paths[2].name}
    poses = {path.name.split(".")[0]: np.zeros((8, 3)) for path in paths}
    results = {
        result.token: result
        for result in evaluate.score_tokens(REFERENCE, tmp_path, poses, "v1.0", list(poses))
    }
    assert not results[broken].valid
    assert results[broken].error == "the metric cache of this hidden scene could not be built (RuntimeError)"
    assert all(result.valid for token, result in results.items() if token != broken)


def test_stale_or_damaged_files_are_rebuilt(
    tmp_path: Path, built: tuple[str, dict[str, MetricCache]]
) -> None:
    token, caches = built
    path = scene_paths(REFERENCE)[token]
    written = save_caches({"v1.1": caches["v1.1"]}, tmp_path)
    assert written == cache_path(tmp_path, token)
    assert load_cache(tmp_path, "v1.1", token, "another scene hash") is None
    written.write_bytes(written.read_bytes()[:-100])
    assert load_cache(tmp_path, "v1.1", token, scene_file_hash(path)) is None
    poses = {token: np.zeros((8, 3))}
    (result,) = score_tokens(REFERENCE, tmp_path, poses, "v1.1", [token])
    assert result.valid
    assert load_cache(tmp_path, "v1.1", token, scene_file_hash(path)) is not None
    # Damaged in place, its size kept: the header no longer parses, and it is rebuilt too.
    data = bytearray(written.read_bytes())
    header = data[16 : 16 + int.from_bytes(data[:8], "little")]
    assert json.loads(header)["versions"]["v1.1"]  # the JSON header the damage breaks
    data[16] = ord("x")
    written.write_bytes(bytes(data))
    assert load_cache(tmp_path, "v1.1", token, scene_file_hash(path)) is None
    (result,) = score_tokens(REFERENCE, tmp_path, poses, "v1.1", [token])
    assert result.valid and load_cache(tmp_path, "v1.1", token, scene_file_hash(path)) is not None


@pytest.mark.parametrize(
    ("field", "value"),
    [("offset", -8), ("offset", 10**9), ("shape", [-1, 8]), ("shape", [10**9]), ("dtype", "|O")],
)
def test_an_array_outside_the_files_bytes_is_never_read(
    tmp_path: Path, built: tuple[str, dict[str, MetricCache]], field: str, value: object
) -> None:
    token, caches = built
    written = save_caches({"v1.1": caches["v1.1"]}, tmp_path)
    scene_hash = scene_file_hash(scene_paths(REFERENCE)[token])
    assert load_cache(tmp_path, "v1.1", token, scene_hash) is not None
    data = written.read_bytes()
    length = int.from_bytes(data[:8], "little")
    header, body = json.loads(data[16 : 16 + length]), data[16 + length :]
    at = header["versions"]["v1.1"]["arrays"]["object_corners"]
    header["arrays"][at][("dtype", "shape", "offset").index(field)] = value
    damaged = json.dumps(header).encode()
    size = 16 + len(damaged) + len(body)
    written.write_bytes(len(damaged).to_bytes(8, "little") + size.to_bytes(8, "little") + damaged + body)
    assert load_cache(tmp_path, "v1.1", token, scene_hash) is None


def test_an_unreadable_scene_file_fails_alone(tmp_path: Path) -> None:
    split = tmp_path / "split"
    (split / "scenes").mkdir(parents=True)
    for path in list(scene_paths(REFERENCE).values())[:3]:
        (split / "scenes" / path.name).write_bytes(path.read_bytes())
    (split / "scenes" / "broken.json").mkdir()  # listed as a scene, cannot be read as one
    failures = evaluate.build_split_cache(split, tmp_path / "cache", list(VERSIONS))
    assert list(failures) == ["broken.json"] and failures["broken.json"].startswith("IsADirectoryError")
    assert len(list((tmp_path / "cache").glob("*.nlc"))) == 3


def test_a_team_never_reads_the_servers_path_of_an_unreadable_hidden_scene(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    split = tmp_path / "hidden-split"
    (split / "scenes").mkdir(parents=True)
    token = next(iter(scene_paths(REFERENCE)))
    (split / "scenes" / f"{token}.json.gz").write_bytes(b"\x1f\x8b damaged gzip")
    with caplog.at_level("WARNING", logger="scorer.evaluate"):
        [result] = evaluate.score_tokens(split, tmp_path / "cache", {token: np.zeros((8, 3))}, "v1.1")
    assert not result.valid and result.error is not None
    assert "unreadable" in result.error and str(tmp_path) not in result.error and "json" not in result.error
    assert str(split) in caplog.text  # the organisers' log keeps the detail
