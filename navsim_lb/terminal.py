"""What every `navsim-lb` subcommand prints through: the stderr console, errors, progress bars, warnings."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import typer
from rich.console import Console
from rich.markup import escape

# Emoji codes off: a team's text (a method name, a token) is printed as written, never ":x:" turned into a glyph
# (and the emoji table, 2 ms of start-up, is never imported).
console = Console(stderr=True, emoji=False)  # messages, warnings, progress
output = Console(emoji=False)  # results: the tables a command prints on stdout


@contextmanager
def progress_bar(description: str, total: int) -> Iterator[Callable[[int], None]]:
    """Yield a callback advancing a progress bar by n items: rich's live bar on a terminal; in a log or a pipe,
    where a bar cannot redraw, one line when the work is done (and rich.progress is not imported)."""
    if not console.is_terminal:
        start, done = time.perf_counter(), 0

        def advance(count: int) -> None:
            nonlocal done
            done += count

        yield advance
        # Not highlighted: where no bar can redraw there are no colours either, and rich's highlighter would
        # compile its regular expressions (milliseconds of a one-token `navsim-lb score`) to colour nothing.
        line = escape(f"{description}: {done}/{total} in {time.perf_counter() - start:.1f} s")
        console.print(line, highlight=False)
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=console, transient=False) as progress:
        task = progress.add_task(description, total=total)
        yield lambda n: progress.advance(task, n)


def fail(message: str) -> typer.Exit:
    """Print `message` (plain text, never markup: it may quote user data) and return the exit to raise."""
    console.print(f"[red]error:[/red] {escape(message)}")
    return typer.Exit(code=2)


def warn(message: str) -> None:
    """Print a warning (plain text, never markup)."""
    console.print(f"[yellow]warning:[/yellow] {escape(message)}")


def warn_about_kernels() -> None:
    """Say so when the OpenBLAS kernels are not the official results' (last bits may differ)."""
    from scorer.blas import kernel_warning

    warning = kernel_warning()
    if warning is not None:
        warn(warning)
