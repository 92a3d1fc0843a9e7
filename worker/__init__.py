"""Celery workers that score submissions: `worker.app` (configuration), `worker.tasks`, `worker.cli`."""

import scorer  # noqa: F401 - first, so that numpy loads the official results' OpenBLAS kernels (scorer.blas)

# Scoring is batch work: where it shares a machine with the API (the demo, a small deployment), the scoring
# consumers yield the CPU to the requests people wait for (`navsim-lb worker --nice`, this by default:
# worker.supervisor; benchmarks/service.py runs the engine alone at the same niceness).
SCORING_NICENESS = 10
