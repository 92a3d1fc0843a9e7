"""Celery workers that score submissions: `worker.app` (configuration), `worker.tasks`, `worker.cli`."""

import scorer  # noqa: F401 - first, so that numpy loads the official results' OpenBLAS kernels (scorer.blas)
