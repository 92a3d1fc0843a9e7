"""Knife-edge vectors: three tokens whose NC or TTC hangs on the last bit of a BLAS `ddot`.

nuPlan's `get_agent_relative_angle` takes `np.dot` and `np.linalg.norm` of 2-vectors; for a target almost
exactly behind the ego, whether the dot product rounds past -1 (arccos NaN, so "behind" is false) depends
on the OpenBLAS kernel. The devkit's results exist under two kernel sets (`fixtures/knife-edge/README.md`).
The engine must give each set's results under that set's kernels: every column equal, bit for bit, in
v1.0 and v1.1 (the versions of those runs). Each run is a fresh process, because OpenBLAS picks its
kernels when it loads.
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest
from devkit_kernels import V1_VERSIONS
from engine_process import run_python, score_in_process

from scorer.blas import DEVKIT_KERNELS, KEEP_VARIABLE, cpu_runs_devkit_kernels
from scorer.metrics import contacts
from scorer.metrics.contacts import AHEAD_ANGLE, BEHIND_ANGLE, SIDE_MARGIN, contact_sides, relative_angle
from scorer.svml_acos import arccos_avx512
from scorer.versions import METRIC_COLUMNS

KNIFE_EDGE = Path(__file__).parent / "fixtures" / "knife-edge"
FAMILIES = ("cv_accel", "cv_decel", "stop")
EXPECTED = {DEVKIT_KERNELS: "expected", "Haswell": "expected-haswell-kernels"}

# The contact of `cv_decel` on 8bedfe2fc5629e39 at 3.6 s: rear axle (x, y, heading) and the object's centroid.
BEHIND_REAR_AXLE = (365444.6067915583, 144656.98124831126, 2.5276294646145665)
BEHIND_TARGET = (365447.5566276066, 144654.9021022819)

ANGLE = f"""
import json
import numpy as np
import scorer
from scorer.blas import blas_kernels
from scorer.metrics.contacts import relative_angle

angle = relative_angle(np.array([{BEHIND_REAR_AXLE}]), np.array([{BEHIND_TARGET}]))[0]
print(json.dumps({{"kernels": list(blas_kernels()), "angle": None if np.isnan(angle) else angle}}))
"""


def _with_kernels(kernels: str) -> dict[str, str]:
    """Return the environment of a run under `kernels`; skip, saying why, where this CPU cannot run them."""
    if kernels == DEVKIT_KERNELS and not cpu_runs_devkit_kernels():
        # Forced onto a CPU without AVX-512, OpenBLAS's SkylakeX kernels stop the process (illegal instruction).
        pytest.skip(f"this CPU has no AVX-512: OpenBLAS's {kernels} kernels cannot run here")
    return {KEEP_VARIABLE: "1", "OPENBLAS_CORETYPE": kernels}


def _ran_with(output: dict, kernels: str) -> dict:
    """Return `output`, or skip where this CPU could not run the kernels asked for."""
    if output["kernels"] != [kernels]:
        pytest.skip(f"this CPU cannot run OpenBLAS's {kernels} kernels (it ran {output['kernels']})")
    return output


def _expected(directory: str) -> dict[tuple[str, str, str], dict]:
    expected = {}
    for family in FAMILIES:
        for version in V1_VERSIONS:
            with gzip.open(KNIFE_EDGE / directory / f"{family}.{version}.jsonl.gz", "rt") as handle:
                expected |= {(family, version, row["token"]): row for row in map(json.loads, handle)}
    return expected


@pytest.mark.parametrize("kernels", list(EXPECTED))
def test_every_column_equals_the_devkit_under_the_same_kernels(kernels: str, tmp_path: Path) -> None:
    output = score_in_process(KNIFE_EDGE, tmp_path / "cache", list(FAMILIES), _with_kernels(kernels))
    rows = _ran_with(output, kernels)["rows"]
    expected = _expected(EXPECTED[kernels])
    assert len(rows) == len(expected) == 18
    mismatches = [
        f"{family} {version} {token}: {column} {metrics[column]!r} != {expected[family, version, token][column]!r}"
        for family, version, token, _, metrics in rows
        for column in METRIC_COLUMNS
        if metrics[column] != expected[family, version, token][column]
    ]
    assert mismatches == []


def test_the_two_kernel_sets_disagree_on_the_three_tokens() -> None:
    """The vectors are only a test if the kernels' answers differ: NC on two tokens, TTC on the third."""
    official, haswell = _expected("expected"), _expected("expected-haswell-kernels")
    differing = {
        (family, token, column)
        for (family, version, token), row in official.items()
        for column in ("no_at_fault_collisions", "time_to_collision_within_bound")
        if row[column] != haswell[family, version, token][column]
    }
    assert differing == {
        ("cv_decel", "8bedfe2fc5629e39", "no_at_fault_collisions"),
        ("stop", "bc55a3d277193f21", "no_at_fault_collisions"),
        ("cv_accel", "05923cd002a9d02f", "time_to_collision_within_bound"),
    }


def test_a_target_almost_exactly_behind_is_nan_under_the_devkit_kernels_as_in_the_devkit() -> None:
    # Official results: an at-fault collision, so "behind" was false, so the devkit's angle was NaN.
    assert _ran_with(run_python(ANGLE, [], _with_kernels(DEVKIT_KERNELS)), DEVKIT_KERNELS)["angle"] is None


def test_the_same_target_is_behind_under_the_haswell_kernels_as_in_the_devkit() -> None:
    # Haswell results: no at-fault collision, so the devkit's angle was above 150 degrees.
    assert _ran_with(run_python(ANGLE, [], _with_kernels("Haswell")), "Haswell")["angle"] > BEHIND_ANGLE


def test_relative_angles_of_plain_cases() -> None:
    rear_axle = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 2.0, np.pi / 2]])
    targets = np.array([[5.0, 0.0], [-5.0, 0.0], [0.0, 0.0], [1.0, 7.0]])
    angles = relative_angle(rear_axle, targets)
    assert angles[0] == 0.0  # straight ahead
    assert angles[1] == np.pi  # exactly behind: dot product exactly -1
    assert np.isnan(angles[2])  # the target on the rear axle: 0 / 0, as nuPlan's
    assert angles[3] == pytest.approx(0.0, abs=1e-15)


def test_relative_angles_are_the_devkits_per_contact_expression_to_the_bit() -> None:
    """Cosines and sines taken on arrays and the norm as the square root of a `ddot` give the bits of nuPlan's
    expression, contact by contact: targets anywhere, almost exactly behind (where `ddot` passes -1 or not) and
    on the rear axle."""
    rng = np.random.default_rng(2)
    count = 3000
    rear_axle = np.column_stack(
        [rng.uniform(3e5, 4e5, count), rng.uniform(1e5, 2e5, count), rng.uniform(-7.0, 7.0, count)]
    )
    targets = rear_axle[:, :2] + rng.uniform(-30.0, 30.0, (count, 2))
    behind = slice(0, 1000)
    targets[behind] = _targets_at(rear_axle[behind], np.full(1000, np.pi), rng.uniform(1.0, 20.0, 1000))
    targets[1000:1010] = rear_axle[1000:1010, :2]
    offsets = targets - rear_axle[:, :2]
    with np.errstate(invalid="ignore", divide="ignore"):
        cosines = [
            np.dot(np.array([np.cos(heading), np.sin(heading)]), offset / np.linalg.norm(offset))
            for offset, heading in zip(offsets, rear_axle[:, 2].tolist(), strict=True)
        ]
        expected = arccos_avx512(np.array(cosines))
    angles = relative_angle(rear_axle, targets)
    assert angles.tobytes() == expected.tobytes()
    assert np.isnan(angles[behind]).any() and not np.isnan(angles[behind]).all()  # both sides of -1 occur


def _exact_sides(rear_axle: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    angles = relative_angle(rear_axle, targets)
    return angles < AHEAD_ANGLE, angles > BEHIND_ANGLE


def _targets_at(rear_axle: np.ndarray, angles: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Return targets at `angles` (signed, radians) from each rear axle's heading, `distance` (m) away."""
    bearing = rear_axle[:, 2] + angles
    return rear_axle[:, :2] + distance[:, None] * np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)


def test_contact_sides_are_the_exact_angles_compared_with_the_thresholds() -> None:
    rng = np.random.default_rng(5)
    count = 4000
    rear_axle = np.column_stack(
        [rng.uniform(3e5, 4e5, count), rng.uniform(1e5, 2e5, count), rng.uniform(-np.pi, np.pi, count)]
    )
    targets = rear_axle[:, :2] + rng.uniform(-60.0, 60.0, (count, 2))
    ahead, behind = contact_sides(rear_axle, targets)
    expected_ahead, expected_behind = _exact_sides(rear_axle, targets)
    assert np.array_equal(ahead, expected_ahead) and np.array_equal(behind, expected_behind)
    assert ahead.any() and behind.any() and not (ahead | behind).all()


@pytest.mark.parametrize("threshold", [AHEAD_ANGLE, BEHIND_ANGLE])
def test_contact_sides_at_near_ties_are_the_exact_ones(threshold: float) -> None:
    """Targets at the threshold angle nudged by a few ulps, where the arrays' cosine and the devkit's fall on
    either side of the threshold's by turns (the exact calls decide), and targets just beyond the margin either
    way (the arrays decide): every comparison is the exact one."""
    rng = np.random.default_rng(3)
    count = 4000
    # Near the origin, an ulp of a coordinate moves the angle far less than the margin.
    rear_axle = np.column_stack(
        [rng.uniform(-50.0, 50.0, count), rng.uniform(-50.0, 50.0, count), rng.uniform(-np.pi, np.pi, count)]
    )
    sign, distance = rng.choice([-1.0, 1.0], count), rng.uniform(1.0, 20.0, count)
    at_threshold = _targets_at(rear_axle, sign * threshold, distance)
    nudged = at_threshold + rng.integers(-3, 4, (count, 2)) * np.spacing(at_threshold)
    # Twice the margin in the cosine, either way: arccos's slope at both thresholds is -1 / sin = -2.
    beyond = [
        _targets_at(rear_axle, sign * (threshold + side * 4.0 * SIDE_MARGIN), distance) for side in (-1, 1)
    ]
    for targets in (at_threshold, nudged, *beyond):
        sides = contact_sides(rear_axle, targets)
        expected = _exact_sides(rear_axle, targets)
        assert np.array_equal(sides[0], expected[0]) and np.array_equal(sides[1], expected[1])


def test_contact_sides_take_the_exact_calls_only_near_a_tie(monkeypatch: pytest.MonkeyPatch) -> None:
    exact: list[int] = []

    def counted(rear_axle: np.ndarray, targets: np.ndarray) -> np.ndarray:
        exact.append(len(targets))
        return relative_angle(rear_axle, targets)

    monkeypatch.setattr(contacts, "relative_angle", counted)
    rear_axle = np.array([[0.0, 0.0, 0.0]] * 3 + [list(BEHIND_REAR_AXLE)])
    targets = np.array([[5.0, 1.0], [-5.0, 1.0], [0.0, 0.0], list(BEHIND_TARGET)])
    ahead, behind = contact_sides(rear_axle, targets)
    # The target on the rear axle (0 / 0) is neither ahead nor behind, as its NaN angle compares in the devkit;
    # the knife-edge one (a cosine at -1 to the last bit, which the kernels decide) as the exact calls say.
    assert ahead[:3].tolist() == [True, False, False] and behind[:3].tolist() == [False, True, False]
    expected = _exact_sides(rear_axle[3:], targets[3:])
    assert ahead[3] == expected[0][0] and behind[3] == expected[1][0]
    assert exact == [2]
