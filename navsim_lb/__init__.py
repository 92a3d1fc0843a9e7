"""The `navsim-lb` command: engine, server and data-import subcommands in one typer app."""

import gc

# Net allocations of objects between two passes of Python's cycle collector (its default: 700). A command's
# start-up (the imports: modules, classes, functions, tens of thousands of objects that live as long as the
# process, none of them garbage) would run it dozens of times, 8 ms of a one-token `navsim-lb score`; this bound
# still keeps what garbage a long run leaves small. The libraries (scorer, server, worker) do not import this
# package: only the command's processes (and its tests) run with it.
COLLECTION_ALLOCATIONS = 50_000
gc.set_threshold(COLLECTION_ALLOCATIONS, *gc.get_threshold()[1:])

import scorer  # noqa: F401 - first, so that numpy loads the official results' OpenBLAS kernels (scorer.blas)
