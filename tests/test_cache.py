"""The metric cache file: exact round trip, rebuilt when its key changes or the file is damaged."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import shapely

from scorer.cache import MetricCache, build_caches, cache_path, load_cache, save_cache
from scorer.evaluate import score_tokens
from scorer.pdm_scorer import ProposalMeasures
from scorer.scene import iter_scenes, scene_file_hash, scene_paths
from scorer.versions import VERSIONS

REFERENCE = Path(__file__).parent / "fixtures" / "reference"


@pytest.fixture(scope="module")
def built() -> tuple[str, dict[str, MetricCache]]:
    scene = next(iter_scenes(REFERENCE))
    return scene.token, build_caches(scene, list(VERSIONS.values()))


def test_round_trip_is_exact(tmp_path: Path, built: tuple[str, dict[str, MetricCache]]) -> None:
    token, caches = built
    path = scene_paths(REFERENCE)[token]
    for version, cache in caches.items():
        save_cache(cache, tmp_path)
        loaded = load_cache(tmp_path, version, token, scene_file_hash(path))
        assert loaded is not None and loaded.key == cache.key and loaded.ego == cache.ego
        for name in ("trajectory", "centerline", "idm_target_velocities"):
            assert np.array_equal(getattr(loaded, name), getattr(cache, name))
        assert loaded.route_lane_ids == cache.route_lane_ids
        assert shapely.equals_exact(loaded.drivable_map.polygons, cache.drivable_map.polygons, 0.0).all()
        present = cache.observation.present
        assert np.array_equal(loaded.observation.present, present)
        assert np.array_equal(loaded.observation.corners, cache.observation.corners, equal_nan=True)
        for field in fields(ProposalMeasures):
            assert np.array_equal(
                getattr(loaded.reference_measures, field.name), getattr(cache.reference_measures, field.name)
            )


def test_stale_or_damaged_files_are_rebuilt(
    tmp_path: Path, built: tuple[str, dict[str, MetricCache]]
) -> None:
    token, caches = built
    path = scene_paths(REFERENCE)[token]
    written = save_cache(caches["v1.1"], tmp_path)
    assert written == cache_path(tmp_path, "v1.1", token)
    assert load_cache(tmp_path, "v1.1", token, "another scene hash") is None
    written.write_bytes(written.read_bytes()[:-100])
    assert load_cache(tmp_path, "v1.1", token, scene_file_hash(path)) is None
    poses = {token: np.zeros((8, 3))}
    (result,) = score_tokens(REFERENCE, tmp_path, poses, "v1.1", [token])
    assert result.valid
    assert load_cache(tmp_path, "v1.1", token, scene_file_hash(path)) is not None
