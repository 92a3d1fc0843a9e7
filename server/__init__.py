"""Evaluation server: REST API, leaderboard and admin around the PDMS and EPDMS engine (FastAPI, SQLAlchemy 2)."""

import scorer  # noqa: F401 - first, so that numpy loads the official results' OpenBLAS kernels (scorer.blas)
