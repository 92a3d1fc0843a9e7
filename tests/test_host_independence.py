"""Workers on different CPUs give the same numbers, as far as numpy's own kernels go.

numpy picks its math kernels by CPU (AVX-512 SVML arctan2 and tan on this host, other code elsewhere). The
engine uses numpy's arctan2 where it is SVML and an emulation of it elsewhere, so the whole run (metric cache with
PDM-Closed, then scoring) must give the same bits with every numpy dispatch target above the baseline
switched off. (OpenBLAS's kernels do move last bits: `scorer.blas` selects the official results' ones and
`test_blas` checks that it does.) On a host without AVX-512 both runs use the same kernels and the
comparison is trivially equal.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
FAMILIES = ("human", "lane_change", "swerve_left_fast", "zigzag", "stop")

RUN = """
import json, sys
from pathlib import Path
import scorer
from numpy._core._multiarray_umath import __cpu_features__
from scorer.evaluate import build_split_cache, score_tokens
from scorer.submission import load_submission
from scorer.versions import VERSIONS

split, cache, families = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3:]
assert build_split_cache(split, cache, list(VERSIONS)) == {}
rows = []
for family in families:
    path = split / "submissions" / f"{family}.json"
    poses = load_submission(path.read_bytes(), path.name).seeds[0]
    for version in VERSIONS:
        rows += [[family, version, r.token, r.valid, r.metrics] for r in score_tokens(split, cache, poses, version)]
print(json.dumps({"avx512": __cpu_features__.get("X86_V4", False), "rows": rows}))
"""


def _scored(cache: Path, environment: dict[str, str]) -> dict[str, object]:
    done = subprocess.run(
        [sys.executable, "-c", RUN, str(REFERENCE), str(cache), *FAMILIES],
        capture_output=True,
        text=True,
        check=False,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1", **environment},
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)  # floats round-trip exactly through JSON


DETECT = "import scorer.geometry as g; print(g.NUMPY_ARCTAN2_IS_SVML)"


def test_numpy_svml_is_detected_and_the_emulation_takes_over_without_it() -> None:
    def detected(environment: dict[str, str]) -> str:
        done = subprocess.run(
            [sys.executable, "-c", DETECT],
            capture_output=True,
            text=True,
            check=True,
            env={**os.environ, **environment},
        )
        return done.stdout.strip()

    assert detected({"NPY_DISABLE_CPU_FEATURES": " ".join(__cpu_dispatch__)}) == "False"
    if "X86_V4" in __cpu_dispatch__ and __cpu_features__.get("X86_V4"):  # numpy runs its AVX-512 kernels here
        assert detected({}) == "True"


def test_results_are_bit_identical_without_avx512_kernels(tmp_path: Path) -> None:
    native = _scored(tmp_path / "native", {})
    generic = _scored(
        tmp_path / "generic",
        {"NPY_DISABLE_CPU_FEATURES": " ".join(__cpu_dispatch__)},
    )
    assert generic["avx512"] is False  # the switch took effect
    assert len(native["rows"]) == len(FAMILIES) * 2 * 40  # type: ignore[arg-type]
    assert generic["rows"] == native["rows"]
