"""`python -m worker ...` is `navsim-lb worker ...` (worker.cli): a worker started by this interpreter."""

import typer

from worker.cli import run_worker

typer.run(run_worker)
