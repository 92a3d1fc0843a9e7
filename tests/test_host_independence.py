"""Workers on different CPUs simulate and score with the same bits, as far as numpy's own kernels go.

numpy picks its math kernels by CPU: on AVX-512 it runs Intel SVML for arctan2, tan, power and others,
elsewhere the C library's. The engine uses numpy's arctan2, tan, power and arccos where they are SVML and an
emulation of them elsewhere (docs/engine.md, "Host dependence and kernels"), so the simulation (the tracker and the
bicycle model) must give every state the same bits for the same input with numpy's AVX-512 dispatch switched
off (an AVX2 host's numpy) and with every dispatch target above the baseline switched off: over a whole run,
the metric cache (PDM-Closed's proposals and reference, the humans) and the submissions' simulations under
every log-replay version, and every result must keep its bits. PDM-Closed's IDM takes (v / v0) ** 10, which
moved the last bit of a few proposals' headings before power was emulated: every simulation now gets the
same input on every path (`test_pdm_closed_proposals_keep_their_bits`). The two-stage weights take numpy's
exp, which is SVML's on AVX-512 and replayed elsewhere: they must be the official ones on every path.

OpenBLAS's kernels move last bits of their own (the tracker's `pinv`): `scorer.blas` selects the official
results' SkylakeX ones where the CPU runs them and `test_blas` checks that it does. So the comparison holds
per kernel set: under SkylakeX, as on the official AVX-512 machines, and under Haswell, as on a host without
AVX-512. On such a host numpy has no AVX-512 path to switch off: the runs compared are alike.
"""

from __future__ import annotations

import os
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest
from engine_process import run_python
from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

from scorer.blas import DEVKIT_KERNELS, KEEP_VARIABLE, cpu_runs_devkit_kernels

FIXTURES = Path(__file__).parent / "fixtures"
SPLITS = (FIXTURES / "reference", FIXTURES / "knife-edge")
AVX512_TARGETS = "X86_V4 AVX512_ICL AVX512_SPR"  # numpy's dispatch targets that run SVML
NUMPY_PATHS = {
    "native": {},
    "without AVX-512": {"NPY_DISABLE_CPU_FEATURES": AVX512_TARGETS},
    "baseline": {"NPY_DISABLE_CPU_FEATURES": " ".join(__cpu_dispatch__)},
}
KERNELS = [DEVKIT_KERNELS, "Haswell"] if cpu_runs_devkit_kernels() else ["Haswell"]
NUMPY_RUNS_SVML = "X86_V4" in __cpu_dispatch__ and bool(__cpu_features__.get("X86_V4"))

# Every split scored in one fresh process under every log-replay version: the sha256 of every simulation's
# input and states (`simulation._simulate`, in call order) and every result row.
SIMULATE_AND_SCORE = """
import hashlib, json, math, sys
from pathlib import Path
import scorer
import scorer.simulation as simulation
from scorer.blas import blas_kernels
from scorer.evaluate import build_split_cache, score_versions
from scorer.geometry import NUMPY_ARCTAN2_IS_SVML
from scorer.submission import load_submission
from scorer.svml_acos import NUMPY_ARCCOS_IS_SVML
from scorer.svml_exp import NUMPY_EXP_IS_SVML
from scorer.svml_pow import NUMPY_POWER_IS_SVML
from scorer.svml_tan import NUMPY_TAN_IS_SVML
from scorer.versions import LOG_REPLAY_VERSIONS

simulations = []
simulate = simulation._simulate

def digest(*arrays):
    return hashlib.sha256(b"".join(array.tobytes() for array in arrays)).hexdigest()

def recorded(poses, initial):
    states = simulate(poses, initial)
    simulations.append([len(states), digest(poses, initial), digest(states)])
    return states

simulation._simulate = recorded
cache, rows = Path(sys.argv[1]), []
for split in map(Path, sys.argv[2:]):
    assert build_split_cache(split, cache, list(LOG_REPLAY_VERSIONS)) == {}
    for path in sorted((split / "submissions").glob("*.json")):
        poses = load_submission(path.read_bytes(), path.name).seeds[0]
        for version, results in score_versions(split, cache, poses, list(LOG_REPLAY_VERSIONS)).items():
            for r in results:
                metrics = {k: None if math.isnan(v) else v for k, v in r.metrics.items()}
                rows.append([split.name, path.stem, version, r.token, r.valid, metrics])
print(json.dumps({
    "svml": [NUMPY_ARCTAN2_IS_SVML, NUMPY_TAN_IS_SVML, NUMPY_POWER_IS_SVML, NUMPY_EXP_IS_SVML, NUMPY_ARCCOS_IS_SVML],
    "kernels": list(blas_kernels()),
    "simulations": simulations,
    "rows": rows,
}))
"""


@cache
def _run(kernels: str, numpy_path: str, cache_dir: Path) -> dict:
    environment = {KEEP_VARIABLE: "1", "OPENBLAS_CORETYPE": kernels, **NUMPY_PATHS[numpy_path]}
    directory = cache_dir / f"{kernels}-{numpy_path}"
    output = run_python(SIMULATE_AND_SCORE, [str(directory), *map(str, SPLITS)], environment)
    assert output["kernels"] == [kernels]
    return output


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("caches")


DETECT = (
    "import scorer.geometry as g, scorer.svml_acos as a, scorer.svml_exp as e, scorer.svml_pow as p,"
    " scorer.svml_tan as t; print(g.NUMPY_ARCTAN2_IS_SVML, t.NUMPY_TAN_IS_SVML, p.NUMPY_POWER_IS_SVML,"
    " e.NUMPY_EXP_IS_SVML, a.NUMPY_ARCCOS_IS_SVML)"
)
SVML_REPLAYS = 5  # arctan2, tan, power, exp, arccos


def test_numpy_svml_is_detected_and_the_emulations_take_over_without_it() -> None:
    def detected(environment: dict[str, str]) -> str:
        done = subprocess.run(
            [sys.executable, "-c", DETECT],
            capture_output=True,
            text=True,
            check=True,
            env={**os.environ, **environment},
        )
        return done.stdout.strip()

    assert detected(NUMPY_PATHS["without AVX-512"]) == " ".join(["False"] * SVML_REPLAYS)
    assert detected(NUMPY_PATHS["baseline"]) == " ".join(["False"] * SVML_REPLAYS)
    if NUMPY_RUNS_SVML:
        assert detected({}) == " ".join(["True"] * SVML_REPLAYS)


# The engine's power (`power_avx512`) on SVML's recorded bits, off its main path too (test_svml_pow).
RECORDED_POWERS = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from scorer.svml_pow import NUMPY_POWER_IS_SVML, power_avx512
from test_svml_pow import recorded_powers
with np.errstate(all="ignore"):
    same = [np.array_equal(power_avx512(b, e).view(np.int64), p.view(np.int64)) for e, b, p in recorded_powers()]
print(json.dumps({"svml": NUMPY_POWER_IS_SVML, "same": all(same)}))
"""


@pytest.mark.parametrize("numpy_path", NUMPY_PATHS)
def test_the_engines_power_gives_svmls_recorded_bits_on_every_numpy_path(numpy_path: str) -> None:
    """The IDM's v / v0 is negative where the ego's speed is: SVML's scalar path, replayed without numpy's SVML."""
    output = run_python(RECORDED_POWERS, [str(Path(__file__).parent)], NUMPY_PATHS[numpy_path])
    assert output == {"svml": NUMPY_RUNS_SVML and numpy_path == "native", "same": True}


def _compared(kernels: str, numpy_path: str, cache_dir: Path) -> tuple[dict, dict]:
    native, other = _run(kernels, "native", cache_dir), _run(kernels, numpy_path, cache_dir)
    assert other["svml"] == [False] * SVML_REPLAYS  # the switch took effect: the emulations ran
    assert native["svml"] == [NUMPY_RUNS_SVML] * SVML_REPLAYS
    assert len(native["simulations"]) == len(other["simulations"])
    return native, other


@pytest.mark.slow
@pytest.mark.parametrize("kernels", KERNELS)
@pytest.mark.parametrize("numpy_path", ["without AVX-512", "baseline"])
def test_every_simulated_state_and_result_keeps_its_bits_on_every_numpy_path(
    kernels: str, numpy_path: str, cache_dir: Path
) -> None:
    native, other = _compared(kernels, numpy_path, cache_dir)
    pairs = list(zip(native["simulations"], other["simulations"], strict=True))
    same_input = [(ours, theirs) for ours, theirs in pairs if ours[:2] == theirs[:2]]
    # Every reference and knife-edge token under every log-replay version, from one cache per process: the
    # submissions' simulations (13 x 40 + 3 x 3 trajectories at least) all see the same input.
    assert sum(rows for rows, _, _ in (ours for ours, _ in same_input)) > 13 * 40 + 3 * 3
    assert [index for index, (ours, theirs) in enumerate(same_input) if ours[2] != theirs[2]] == []
    assert len(native["rows"]) == 3 * (13 * 40 + 3 * 3)
    assert other["rows"] == native["rows"]


# The submissions' simulated states of every official v2.2 token (fixtures/epdms, 1,846 tokens made on an
# AVX-512 host under the SkylakeX kernels), simulated in one call: the tokens whose states differ.
OFFICIAL_STATES = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
import scorer
from epdms_reference import rows, scene
from scorer.simulation import simulate
from scorer.submission import load_submission
from scorer.trajectory import agent_references, initial_state

submissions = {}
def poses(row):
    path = row.scene_path.parent.parent / "submissions" / f"{row.family}.json"
    if path not in submissions:
        submissions[path] = load_submission(path.read_bytes(), path.name).seeds[0]
    return submissions[path][row.token]

official = rows()
frames = [scene(row.scene_path).current_frame for row in official]
initial = np.array([initial_state(frame.ego) for frame in frames])
t0_us = np.array([frame.timestamp_us for frame in frames])
states = simulate(agent_references(initial, t0_us, np.array([poses(row) for row in official])), initial)
expected = np.array([row.diagnostics["agent_states"] for row in official], dtype=np.float64)
differing = (states != expected).any(axis=(1, 2))
print(json.dumps({"count": len(official), "differing": [[r.family, r.token] for r, d in zip(official, differing) if d]}))
"""
# Its official row was simulated from a submission 1.1e-16 away from the stored one (fixtures/epdms/README.md).
REGENERATED_SUBMISSION = ["human_noise", "58c89d98cb15536f8"]


@pytest.mark.slow
@pytest.mark.skipif(not cpu_runs_devkit_kernels(), reason="the official states need the SkylakeX kernels")
@pytest.mark.parametrize("numpy_path", list(NUMPY_PATHS))
def test_every_submission_is_simulated_as_the_official_v2_2_results_on_every_numpy_path(
    numpy_path: str,
) -> None:
    output = run_python(OFFICIAL_STATES, [str(Path(__file__).parent)], NUMPY_PATHS[numpy_path])
    assert output["count"] == 1846
    assert output["differing"] == [REGENERATED_SUBMISSION]


@pytest.mark.slow
def test_pdm_closed_proposals_keep_their_bits(cache_dir: Path) -> None:
    native, other = _compared(KERNELS[0], "without AVX-512", cache_dir)
    assert [ours[1] for ours in native["simulations"]] == [theirs[1] for theirs in other["simulations"]]


# The two-stage weights of every reference family (fixtures/two-stage, official values from an AVX-512 host):
# the tokens whose weight or weight detail differs. Their Gaussians are SVML's exp on every path (numpy's exp
# without its AVX-512 path moved 233 of them).
TWO_STAGE_WEIGHTS = """
import json, sys
sys.path.insert(0, sys.argv[1])
import scorer
from two_stage_reference import FAMILIES, SPLIT, aggregation_input, official_tokens
from scorer.two_stage.aggregate import aggregate_two_stage

differing = []
for family in FAMILIES:
    result, lines = aggregate_two_stage(aggregation_input(family), SPLIT), official_tokens(family)
    differing += [[family, t] for t, weight in result.weights.items() if weight != lines[t]["weight"]]
    differing += [[family, t] for t, d in result.weight_detail.items() if d != lines[t]["weight_detail"]]
print(json.dumps({"differing": differing}))
"""


@pytest.mark.parametrize("numpy_path", list(NUMPY_PATHS))
def test_the_two_stage_weights_are_the_official_ones_on_every_numpy_path(numpy_path: str) -> None:
    output = run_python(TWO_STAGE_WEIGHTS, [str(Path(__file__).parent)], NUMPY_PATHS[numpy_path])
    assert output["differing"] == []
