"""Batching never changes a token's result: many tokens per call, or proposals measured apart and joined,
give exactly what `score_proposals` gives for each token alone (reference scenes, devkit-simulated poses).
"""

from __future__ import annotations

import gzip
import json
from dataclasses import replace
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from engine_scoring import score_proposals

from scorer import pdm_scorer
from scorer.drivable_map import build_drivable_map
from scorer.metrics.ego_areas import ego_areas
from scorer.metrics.ego_box import repeated_from
from scorer.observation import observe_scene
from scorer.pdm_scorer import (
    EgoRows,
    MeasureSettings,
    ProposalMeasures,
    ProposalScores,
    join_measures,
    measure_alike,
    measure_batch,
    score_batch,
    score_measures,
    ttc_horizons,
)
from scorer.scene import load_scene
from scorer.versions import METRIC_COLUMNS, get_version

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
FAMILIES = ("human", "swerve_left", "zigzag", "hard_brake")
RESULTS = (
    *METRIC_COLUMNS,
    "progress_raw",
    "collision_index",
    "collision_object",
    "ttc_index",
    "ttc_object",
    "ego_areas",
)


@cache
def _scene_inputs(token: str) -> tuple:
    scene = load_scene(REFERENCE / "scenes" / f"{token}.json.gz")
    return observe_scene(scene), build_drivable_map(scene)


@cache
def _tokens(version: str) -> tuple:
    """(states (2, 41, 11), observation, map, centerline, route lane ids) per token and family."""
    cases = []
    for family in FAMILIES:
        with gzip.open(REFERENCE / "expected" / f"{family}.{version}.jsonl.gz", "rt") as handle:
            for row in map(json.loads, handle):
                states = np.zeros((2, 41, 11))
                states[0, :, :3] = row["diagnostics"]["pdm_simulated"]
                states[1, :, :3] = row["diagnostics"]["pred_simulated"]
                states[..., 3] = (
                    np.hypot(*np.diff(states[..., :2], axis=1, prepend=states[:, :1, :2]).T).T / 0.1
                )
                cached = row["cache"]
                cases.append(
                    (
                        states,
                        *_scene_inputs(row["token"]),
                        np.asarray(cached["centerline"])[:, :2],
                        cached["route_lane_ids"],
                    )
                )
    return tuple(cases)


def _same(first: ProposalScores, second: ProposalScores) -> bool:
    return all(np.array_equal(getattr(first, name), getattr(second, name)) for name in RESULTS)


@pytest.mark.parametrize("version", ["v1.0", "v1.1"])
def test_a_batch_scores_each_token_as_alone(version: str) -> None:
    config = get_version(version).evaluation
    cases = _tokens(version)
    batch = score_batch(*(list(column) for column in zip(*cases, strict=True)), config)
    assert batch.score.shape == (len(cases), 2)
    singles = [score_proposals(*case, config) for case in cases]
    assert all(_same(batch.token(index), single) for index, single in enumerate(singles))


@pytest.mark.parametrize("version", ["v1.0", "v1.1"])
def test_proposals_measured_apart_and_joined_score_as_together(version: str) -> None:
    config = get_version(version).evaluation
    cases = _tokens(version)
    states, observations, maps, centerlines, routes = (list(column) for column in zip(*cases, strict=True))
    states = np.stack(states)
    reference = measure_batch(states[:, :1], observations, maps, centerlines, routes, config)
    submitted = measure_batch(states[:, 1:], observations, maps, centerlines, routes, config)
    joined = score_measures(join_measures([reference, submitted]), config)
    assert _same(joined, score_batch(states, observations, maps, centerlines, routes, config))


def test_configs_measured_together_get_what_each_gets_alone() -> None:
    """`measure_alike` shares what no setting changes (areas, progress), NC and TTC's contacts over the longest
    horizon per observation; every setting's measures, whichever observation it reads, are still those it gets
    measured alone, bit for bit."""
    cases = _tokens("v1.1")
    states, observations, maps, centerlines, routes = (list(column) for column in zip(*cases, strict=True))
    v1 = MeasureSettings.of(get_version("v1.1").evaluation)
    settings = [
        v1,
        v1._replace(ttc_evaluated_steps=32),  # v2.2's TTC horizon: a prefix of v1's contacts
        v1._replace(ttc_evaluated_steps=12, stopped_speed_threshold=1.0),
        v1._replace(ddc_excludes_intersections=True, comfort_at_centre=True, lane_keeping=(0.5, 2.0)),
        v1,
        v1,  # the last two observe no object
        v1._replace(ttc_evaluated_steps=32),
    ]
    # Another way of observing (as v2.2 drops the tracks on the ego): each token's observation emptied.
    empty = [
        replace(
            observation,
            tokens=(),
            object_types=(),
            is_agent=observation.is_agent[:0],
            first_speed=observation.first_speed[:0],
            present=observation.present[:, :0],
            boxes=observation.boxes[:0],
        )
        for observation in observations
    ]
    observed = [observations] * 5 + [empty] * 2
    rest = (maps, centerlines, routes)
    together = measure_alike(np.stack(states), observed, *rest, settings)
    for setting, seen, measures in zip(settings, observed, together, strict=True):
        (alone,) = measure_alike(np.stack(states), [seen], *rest, [setting])
        for name in ProposalMeasures._fields:
            assert np.array_equal(getattr(measures, name), getattr(alone, name)), (setting, name)
    assert any(0.0 in measures.time_to_collision_within_bound for measures in together)  # TTC is exercised
    # Without objects TTC finds nothing: the two observations were measured apart.
    assert (together[5].time_to_collision_within_bound == 1.0).all()


def test_ego_rows_are_each_tokens_proposals_in_order() -> None:
    cases = _tokens("v1.1")[:2]
    states, _, maps, centerlines, routes = (list(column) for column in zip(*cases, strict=True))
    ego = EgoRows.of(np.stack(states), maps, centerlines, routes)
    assert ego.row_token.tolist() == [0, 0, 1, 1]
    assert np.array_equal(ego.per_token(ego.rows), np.stack(states))
    with pytest.raises(ValueError, match="expected shape"):
        EgoRows.of(np.stack(states)[:, :, :-1], maps, centerlines, routes)


def test_ttc_horizons_are_those_of_the_settings_reading_each_observation() -> None:
    v1 = MeasureSettings.of(get_version("v1.1").evaluation)
    readers = [
        (v1, (1, 2)),
        (v1._replace(ttc_evaluated_steps=32), (1, 2)),
        (v1._replace(ttc_evaluated_steps=12), (3, 4)),
        (v1, (1, 2)),
    ]
    assert ttc_horizons(readers) == {(1, 2): [32, v1.ttc_evaluated_steps], (3, 4): [12]}


def test_centres_in_intersections_are_found_once_and_only_when_a_setting_reads_them(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """v1 reads no intersection; v2.2's DDC and LK both do, from one query however many settings read it."""
    found = []
    query = pdm_scorer.in_intersection
    monkeypatch.setattr(pdm_scorer, "in_intersection", lambda *args: found.append(args) or query(*args))
    states, observations, maps, centerlines, routes = (
        list(column) for column in zip(*_tokens("v1.1"), strict=True)
    )
    v1, v2 = (MeasureSettings.of(get_version(version).evaluation) for version in ("v1.1", "v2.2"))
    measure_alike(np.stack(states), [observations], maps, centerlines, routes, [v1])
    assert not found
    measure_alike(np.stack(states), [observations] * 3, maps, centerlines, routes, [v1, v2, v2])
    assert len(found) == 1


def test_comfort_shared_with_an_earlier_batch_is_each_batchs_own() -> None:
    rng = np.random.default_rng(11)
    # Comfort series (B, P, 41, 4): gentle accelerations and headings pass, a jolt of 6 m/s^2 fails.
    earlier = np.cumsum(rng.normal(0.0, 0.002, (8, 2, 41, 4)), axis=2)
    later = earlier.copy()
    later[[1, 4], 1, 20:, 0] += 6.0  # two tokens' agents differ, and fail where the earlier batch's pass
    later[6, 0, 0, 0] = -later[6, 0, 0, 0]  # another token differs in a single bit of its reference
    known: list[tuple[np.ndarray, np.ndarray]] = []
    first = pdm_scorer.comfort_of(earlier, known)
    second = pdm_scorer.comfort_of(later, known)
    assert np.array_equal(first, pdm_scorer.is_comfortable(earlier, 0.1)) and first.all()
    assert np.array_equal(second, pdm_scorer.is_comfortable(later, 0.1))
    assert not second[[1, 4], 1].any()
    assert len(known) == 2


def test_repeated_from_names_the_first_step_of_each_run_of_equal_bits() -> None:
    values = np.array(
        [
            [[1.0, 2.0], [1.0, 2.0], [1.0, 3.0], [1.0, 3.0], [1.0, 3.0]],
            [[0.0, 0.0], [-0.0, 0.0]] * 2 + [[0.0, 0.0]],
        ]
    )
    assert repeated_from(values).tolist() == [[0, 0, 2, 2, 2], [0, 1, 2, 3, 4]]


def _standing(from_step: int) -> tuple:
    """The v1.1 cases' proposals (B, 2, 41, 11) standing still from `from_step` on, and the other inputs."""
    cases = _tokens("v1.1")
    states, observations, maps, centerlines, routes = (list(column) for column in zip(*cases, strict=True))
    standing = np.stack(states)
    standing[:, :, from_step:] = standing[:, :, from_step : from_step + 1]
    standing[:, :, from_step:, 3] = 0.0
    return standing, observations, maps, centerlines, routes


def test_a_standing_box_has_the_ego_areas_of_its_step_measured_alone() -> None:
    """A box that repeats the step before's takes that step's flags (`repeated_from`): each step measured on
    its own gives the same."""
    standing, _, maps, centerlines, routes = _standing(20)
    ego = EgoRows.of(standing, maps, centerlines, routes)
    alone = [
        ego_areas(ego.points[:, step : step + 1], ego.bounds[:, step : step + 1], ego.row_token, ego.maps)
        for step in range(standing.shape[2])
    ]
    assert np.array_equal(ego.areas, np.concatenate(alone, axis=1))


def test_proposals_stopped_throughout_have_no_collision_or_ttc_infraction() -> None:
    """A stopped ego is never at fault (NC) and its states are skipped (TTC), whatever it touches."""
    standing, observations, maps, centerlines, routes = _standing(0)
    measures = measure_batch(
        standing, observations, maps, centerlines, routes, get_version("v1.1").evaluation
    )
    assert (measures.no_at_fault_collisions == 1.0).all() and (measures.collision_index == -1).all()
    assert (measures.time_to_collision_within_bound == 1.0).all() and (measures.ttc_index == -1).all()
