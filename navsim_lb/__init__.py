"""The `navsim-lb` command: engine, server and data-import subcommands in one typer app."""

import scorer  # noqa: F401 - first, so that numpy loads the official results' OpenBLAS kernels (scorer.blas)
