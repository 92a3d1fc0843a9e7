"""Score reference-style directories (scenes/, submissions/) in a fresh Python process.

CPU dispatch decides last bits, and both numpy and OpenBLAS choose their kernels when they load, so a test
that compares kernels runs the engine in a child process with its own environment.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

SCORE = """
import json, sys
from pathlib import Path
import scorer
from numpy._core._multiarray_umath import __cpu_features__
from scorer.blas import blas_kernels
from scorer.evaluate import build_split_cache, score_tokens
from scorer.submission import load_submission
from scorer.versions import VERSIONS

split, cache, families = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3:]
assert build_split_cache(split, cache, list(VERSIONS)) == {}
rows = []
for family in families:
    path = split / "submissions" / f"{family}.json"
    poses = load_submission(path.read_bytes(), path.name).seeds[0]
    for version in ("v1.0", "v1.1"):  # the versions of the knife-edge results
        rows += [[family, version, r.token, r.valid, r.metrics] for r in score_tokens(split, cache, poses, version)]
print(json.dumps({"avx512": __cpu_features__.get("X86_V4", False), "kernels": list(blas_kernels()), "rows": rows}))
"""


def run_python(script: str, arguments: list[str], environment: dict[str, str]) -> dict:
    """Run `script` with `arguments` in a fresh interpreter (one OpenBLAS thread) and return its JSON output."""
    done = subprocess.run(
        [sys.executable, "-c", script, *arguments],
        capture_output=True,
        text=True,
        check=False,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1", **environment},
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)  # floats round-trip exactly through JSON


def score_in_process(split: Path, cache: Path, families: list[str], environment: dict[str, str]) -> dict:
    """Return {"avx512", "kernels", "rows": [[family, version, token, valid, metrics], ...]} of a fresh run."""
    return run_python(SCORE, [str(split), str(cache), *families], environment)
