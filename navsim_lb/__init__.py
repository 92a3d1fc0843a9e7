"""The `navsim-lb` command: engine, server and data-import subcommands in one typer app."""
