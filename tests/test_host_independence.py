"""Workers on different CPUs give the same numbers, as far as numpy's own kernels go.

numpy picks its math kernels by CPU (AVX-512 SVML arctan2 and tan on this host, other code elsewhere). The
engine uses numpy's arctan2 where it is SVML and an emulation of it elsewhere, so the whole run (metric cache with
PDM-Closed, then scoring) must give the same bits with every numpy dispatch target above the baseline
switched off. (OpenBLAS's kernels do move last bits: `scorer.blas` selects the official results' ones and
`test_blas` checks that it does.) On a host without AVX-512 both runs use the same kernels and the
comparison is trivially equal.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from engine_process import score_in_process
from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

REFERENCE = Path(__file__).parent / "fixtures" / "reference"
FAMILIES = ("human", "lane_change", "swerve_left_fast", "zigzag", "stop")


def _scored(cache: Path, environment: dict[str, str]) -> dict[str, object]:
    return score_in_process(REFERENCE, cache, list(FAMILIES), environment)


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
