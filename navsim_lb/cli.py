"""Entry point of `navsim-lb`: each room registers its own subcommands.

`pip install navsim-leaderboard` gives the engine and a team's commands (score, regress, submit, ...; plot
draws with the `[plot]` extra); the server's and the worker's need the `[server]` extra. Without it they stay
listed, and running one says what to install rather than "no such command".
"""

from __future__ import annotations

import atexit
import copy
import gc
import os
import sys
import threading
from collections.abc import Callable, Sequence
from functools import cache
from importlib.util import find_spec
from typing import Annotated, NoReturn

import typer
from typer.main import get_command_name

from navsim_lb import engine_cli
from navsim_lb.terminal import fail, output

SERVER_EXTRA = "pip install 'navsim-leaderboard[server]'"
# What server.cli, worker.cli and demo register (tests/test_packaging.py checks it).
SERVER_COMMANDS = ("serve", "worker", "demo", "db", "admin")
# The extra installs all or nothing: these modules, which its commands start with, stand for it.
SERVER_MODULES = ("fastapi", "uvicorn", "sqlalchemy", "alembic", "celery", "pydantic_settings")


def _missing_server_module() -> str | None:
    """Return a module of the `[server]` extra that is not installed, None when it is (the commands import
    their libraries lazily, so importing them proves nothing; finding a module does not import it)."""
    return next((name for name in SERVER_MODULES if find_spec(name) is None), None)


def _install_hint(name: str, missing_module: str) -> Callable[[], None]:
    """Return a command standing for the server command `name`: it says which extra it needs."""

    def needs_server() -> None:
        raise fail(
            f"`navsim-lb {name}` needs the server's dependencies, not installed here "
            f"(no module {missing_module!r}): {SERVER_EXTRA}"
        )

    return needs_server


def _register_install_hints(app: typer.Typer, missing_module: str) -> None:
    """Register each server command as one that says which extra it needs, whatever its arguments."""
    for name in SERVER_COMMANDS:
        app.command(
            name,
            help=f"(needs the server: {SERVER_EXTRA})",
            context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
        )(_install_hint(name, missing_module))


def _print_version(asked: bool) -> None:
    if asked:
        from importlib.metadata import version

        from scorer import ENGINE_VERSION

        output.print(f"navsim-lb {version('navsim-leaderboard')} (engine {ENGINE_VERSION})")
        raise typer.Exit()


def _options(
    show_version: Annotated[
        bool,
        typer.Option("--version", help="Print the version and exit.", callback=_print_version, is_eager=True),
    ] = False,
) -> None:
    """NAVSIM Leaderboard: PDM Score engine, evaluation server and data tools."""


def _engine_application() -> typer.Typer:
    """Return the application with the engine's commands alone (its options and help are the whole one's)."""
    engine = typer.Typer(no_args_is_help=True)
    engine.callback()(_options)
    engine_cli.register(engine)
    return engine


@cache
def whole_application() -> typer.Typer:
    """Return the application with every room's commands, the engine's first."""
    from navsim_lb import client, demo, openscene_cli

    whole = _engine_application()
    openscene_cli.register(whole)
    client.register(whole)
    missing_server_module = _missing_server_module()
    if missing_server_module is None:
        from server import cli as server_cli
        from worker import cli as worker_cli

        server_cli.register(whole)
        worker_cli.register(whole)
        demo.register(whole)
    else:
        _register_install_hints(whole, missing_server_module)
    return whole


def __getattr__(name: str) -> typer.Typer:
    """`app`: the whole application, built when first asked for (the console script builds less)."""
    if name == "app":
        return whole_application()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _only(application: typer.Typer, name: str) -> typer.Typer | None:
    """Return `application` holding only its command or group `name`, None when it has none of that name."""
    commands = [
        info
        for info in application.registered_commands
        if (info.name or get_command_name(info.callback.__name__ if info.callback else "")) == name
    ]
    groups = [info for info in application.registered_groups if info.name == name]
    if not commands and not groups:
        return None
    # Its callback keeps it a group: `navsim-lb score ...` still names the command.
    single = copy.copy(application)
    single.registered_commands, single.registered_groups = commands, groups
    return single


def application(arguments: Sequence[str]) -> typer.Typer:
    """Return the application holding only the command or group that `arguments` (without the program's name)
    start with, or the whole one when they start with no command's name (an option, a typo, completion).

    Before it parses anything, typer builds every command from its signature: 40 ms of a one-token
    `navsim-lb score` on a slow host, for the commands it does not run. An engine command does not even
    import the other rooms (2 ms). Options, usage and errors are the whole application's.
    """
    name = arguments[0] if arguments else ""
    single = _only(_engine_application(), name) or _only(whole_application(), name)
    return single or whole_application()


def main() -> None:
    """Run `navsim-lb` (the console script). When the command is done, the process ends here (`leave`)."""
    code: str | int | None = None
    try:
        application(sys.argv[1:])()
    except SystemExit as leaving:
        code = leaving.code
    finally:
        # On its way out Python runs the cycle collector over every object still alive, more than once: with
        # numpy's, typer's and rich's that is 25 ms of a one-token `navsim-lb score`. Frozen objects are out of
        # its sight (where the process still ends the usual way).
        gc.freeze()
    leave(code)


def leave(code: str | int | None) -> NoReturn:
    """End the process with exit status `code` once the command is done, skipping the interpreter's teardown.

    The command has done its work and closed its files; what Python's exit would still do is wait for other
    threads, run what atexit registered, flush the standard streams, then tear the interpreter down: free
    every module and object one by one (6 ms of a one-token `navsim-lb score`), memory the OS reclaims with
    the process anyway. This does the first three and leaves the rest to the OS. Where it cannot be sure that
    is all (another thread still running, an exit status that is a message, a stream that cannot be
    flushed, as into a closed pipe), Python exits as usual.
    """
    if isinstance(code, int | None) and threading.active_count() == 1:
        atexit._run_exitfuncs()  # once: they are cleared, so an exit as usual below does not run them again
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        except (OSError, ValueError):
            sys.exit(code)
        os._exit(code or 0)
    sys.exit(code)
