"""What every `navsim-lb` subcommand prints through: the stderr console, errors, progress bars, warnings, tables.

On a terminal rich draws colours, live bars and tables. In a log or a pipe there are no colours and no bar can
redraw: the messages, the one progress line and the tables a command prints most often (`say`, `fail`, `warn`,
`progress_bar`, `print_table`) are written as plain text, and rich, 17 ms of a one-token `navsim-lb score`, is
not imported. What prints rich markup or rich objects goes through `console` and `output`, rich consoles built on
first use.
"""

from __future__ import annotations

import os
import sys
import textwrap
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from functools import cache
from typing import IO, TYPE_CHECKING, Any, NamedTuple

import typer

if TYPE_CHECKING:
    from rich.console import Console
    from rich.table import Table

# Variables under which rich may call a stream a terminal though it is not one (or not one though it is):
# where one is set, rich itself decides.
RICH_TERMINAL_VARIABLES = ("FORCE_COLOR", "NO_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE", "JUPYTER_COLUMNS")


class LazyConsole:
    """A rich console of stderr or stdout, built (and rich imported) when something is printed through it."""

    def __init__(self, stderr: bool) -> None:
        self.stderr = stderr

    @property
    def stream(self) -> IO[str]:
        """The stream now (looked up at each print: a test runner swaps sys.stdout and sys.stderr)."""
        return sys.stderr if self.stderr else sys.stdout

    @property
    def rich(self) -> Console:
        return _rich_console(self.stderr)

    @property
    def is_terminal(self) -> bool:
        """Whether rich would draw on the stream (colours, live bars), asked of rich only where it might differ
        from the stream's own answer."""
        if any(name in os.environ for name in RICH_TERMINAL_VARIABLES):
            return self.rich.is_terminal
        isatty = getattr(self.stream, "isatty", None)
        return bool(isatty and isatty())

    def print(self, *objects: Any, **options: Any) -> None:
        """Print rich markup or rich objects (rich's `Console.print`)."""
        self.rich.print(*objects, **options)

    def plain(self, text: str) -> None:
        """Print `text` as written, on a line of its own."""
        self.stream.write(text + "\n")


@cache
def _rich_console(stderr: bool) -> Console:
    from rich.console import Console

    # Emoji codes off: a team's text (a method name, a token) is printed as written, never ":x:" turned into a
    # glyph (and the emoji table, 2 ms, is never imported).
    return Console(stderr=stderr, emoji=False)


console = LazyConsole(stderr=True)  # messages, warnings, progress
output = LazyConsole(stderr=False)  # results: the tables a command prints on stdout


def escape(text: str) -> str:
    """Return `text` with rich markup escaped, to print it as written among markup."""
    from rich.markup import escape as rich_escape

    return rich_escape(text)


def say(message: str) -> None:
    """Print a message on stderr (plain text, never markup: it may quote a path or user data)."""
    if console.is_terminal:
        console.print(escape(message))
    else:
        console.plain(message)


@contextmanager
def progress_bar(description: str, total: int) -> Iterator[Callable[[int], None]]:
    """Yield a callback advancing a progress bar by n items: rich's live bar on a terminal; in a log or a pipe,
    where a bar cannot redraw, one line when the work is done."""
    if not console.is_terminal:
        start, done = time.perf_counter(), 0

        def advance(count: int) -> None:
            nonlocal done
            done += count

        yield advance
        console.plain(f"{description}: {done}/{total} in {time.perf_counter() - start:.1f} s")
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
    with Progress(*columns, console=console.rich, transient=False) as progress:
        task = progress.add_task(description, total=total)
        yield lambda n: progress.advance(task, n)


class TextTable(NamedTuple):
    """A table of plain text: a title, a header and rows (the first column a label, the others numbers), a
    caption. `print_table` draws it."""

    title: str
    caption: str
    rows: Sequence[Sequence[str]]  # the header first


def _padding(table: TextTable) -> int:
    """Columns are a space apart and, below 12 columns, one more: "100.0" in every column still fits 80 columns
    (a v2.2 summary has thirteen)."""
    return 1 if len(table.rows[0]) < 12 else 0


def rich_table(table: TextTable) -> Table:
    """Return `table` as a rich table that fits an 80-column terminal (no vertical rules, numbers right)."""
    from rich import box
    from rich.table import Table

    header, *body = table.rows
    drawn = Table(
        title=escape(table.title),  # plain text: it quotes the method
        caption=escape(table.caption),
        box=box.SIMPLE_HEAD,
        show_edge=False,
        pad_edge=False,
        padding=(0, _padding(table), 0, 0),
    )
    for index, column in enumerate(header):
        drawn.add_column(column, justify="left" if index == 0 else "right", no_wrap=True)
    for row in body:
        drawn.add_row(*row)
    return drawn


def plain_table(table: TextTable) -> str:
    """Return `table` laid out as rich draws it in a log or a pipe: the title centred above, the header ruled
    off, numbers right-aligned, the caption centred below (wrapped to the table's width); no trailing spaces."""
    widths = [max(len(row[index]) for row in table.rows) for index in range(len(table.rows[0]))]
    gap = " " * (1 + _padding(table))

    def line(row: Sequence[str]) -> str:
        cells = [
            cell.ljust(width) if index == 0 else cell.rjust(width)
            for index, (cell, width) in enumerate(zip(row, widths, strict=True))
        ]
        return gap.join(cells).rstrip()

    width = sum(widths) + len(gap) * (len(widths) - 1)
    header, *body = table.rows

    def centred(text: str) -> list[str]:
        return [" " * ((width - len(part)) // 2) + part for part in textwrap.wrap(text, width)]

    lines = [*centred(table.title), line(header), "─" * width, *map(line, body), *centred(table.caption)]
    return "\n".join(lines)


def print_table(table: TextTable) -> None:
    """Print `table` on stdout: rich's on a terminal, plain text in a log or a pipe."""
    if output.is_terminal:
        output.print(rich_table(table))
    else:
        output.plain(plain_table(table))


def fail(message: str) -> typer.Exit:
    """Print `message` (plain text, never markup: it may quote user data) and return the exit to raise."""
    _labelled("red", "error", message)
    return typer.Exit(code=2)


def warn(message: str) -> None:
    """Print a warning (plain text, never markup)."""
    _labelled("yellow", "warning", message)


def _labelled(colour: str, label: str, message: str) -> None:
    if console.is_terminal:
        console.print(f"[{colour}]{label}:[/{colour}] {escape(message)}")
    else:
        console.plain(f"{label}: {message}")


def warn_about_kernels() -> None:
    """Say so when the OpenBLAS kernels are not the official results' (last bits may differ)."""
    from scorer.blas import kernel_warning

    warning = kernel_warning()
    if warning is not None:
        warn(warning)
