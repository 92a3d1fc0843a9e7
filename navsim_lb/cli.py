"""Entry point of `navsim-lb`: each room registers its own subcommands."""

from __future__ import annotations

import typer

from navsim_lb import client, demo, engine_cli, openscene_cli
from server import cli as server_cli
from worker import cli as worker_cli

app = typer.Typer(
    help="NAVSIM Leaderboard: PDM Score engine, evaluation server and data tools.", no_args_is_help=True
)
engine_cli.register(app)
openscene_cli.register(app)
server_cli.register(app)
worker_cli.register(app)
client.register(app)
demo.register(app)
