"""The console script's entry point: only the command named is built, and the whole application otherwise."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from typer.main import get_command
from typer.testing import CliRunner

from navsim_lb.cli import app, application
from scorer import ENGINE_VERSION

runner = CliRunner()
NAVSIM_LB = str(Path(sys.executable).with_name("navsim-lb"))


def _commands(arguments: list[str]) -> list[str]:
    return sorted(get_command(application(arguments)).commands)  # type: ignore[attr-defined]


def test_a_command_or_group_named_first_is_built_alone() -> None:
    assert _commands(["score", "split", "entry.json"]) == ["score"]
    assert _commands(["import-openscene", "--help"]) == ["import-openscene"]
    assert _commands(["worker"]) == ["worker"]
    assert _commands(["db", "upgrade"]) == ["db"]
    assert sorted(get_command(application(["db"])).commands["db"].commands) == [
        "current",
        "downgrade",
        "upgrade",
    ]  # type: ignore[attr-defined]


def test_anything_else_gets_every_command() -> None:
    everything = sorted(get_command(app).commands)  # type: ignore[attr-defined]
    assert {"score", "submit", "serve", "db", "admin"} <= set(everything)
    for arguments in ([], ["--help"], ["--version"], ["scor"], ["split", "score"]):
        assert application(arguments) is app, arguments


def test_the_command_alone_runs_as_in_the_whole_application() -> None:
    alone = runner.invoke(application(["score"]), ["score", "--help"])
    whole = runner.invoke(app, ["score", "--help"])
    assert alone.exit_code == whole.exit_code == 0
    assert alone.output == whole.output and "submission file" in alone.output
    unknown = runner.invoke(application(["scor"]), ["scor"])
    assert unknown.exit_code == 2 and "No such command" in unknown.output


def test_the_installed_script_runs_a_command_and_says_its_version() -> None:
    version = subprocess.run([NAVSIM_LB, "--version"], capture_output=True, text=True, check=True)
    assert version.stdout.startswith("navsim-lb ") and f"(engine {ENGINE_VERSION})" in version.stdout
    listing = subprocess.run([NAVSIM_LB, "--help"], capture_output=True, text=True, check=True)
    assert "PDM Score engine" in listing.stdout and "score" in listing.stdout and "admin" in listing.stdout
    failing = subprocess.run(
        [NAVSIM_LB, "score", "/no/such/split", "x.json"], check=False, capture_output=True, text=True
    )
    assert failing.returncode == 2 and "/no/such/split" in failing.stderr


def test_the_package_runs_as_a_module_as_the_script_does() -> None:
    """`python -m navsim_lb` is the same command, named as it was called."""
    version = subprocess.run(
        [sys.executable, "-m", "navsim_lb", "--version"], capture_output=True, text=True, check=True
    )
    assert f"(engine {ENGINE_VERSION})" in version.stdout
    listing = subprocess.run(
        [sys.executable, "-m", "navsim_lb", "--help"], capture_output=True, text=True, check=True
    )
    assert "python -m navsim_lb" in listing.stdout and "score" in listing.stdout


EXIT_PROBE = """
import atexit, gc, sys
atexit.register(lambda: print("frozen at exit:", gc.get_freeze_count()))
from navsim_lb.cli import main
sys.argv = ["navsim-lb", "--version"]
main()
"""


def test_the_script_leaves_its_objects_to_the_os_at_exit() -> None:
    """Exit's cycle collection over every live object is skipped (gc.freeze), and exit still runs what atexit
    registered and flushes what was printed."""
    done = subprocess.run([sys.executable, "-c", EXIT_PROBE], capture_output=True, text=True, check=True)
    lines = done.stdout.splitlines()
    assert lines[0].startswith("navsim-lb ")
    frozen = int(lines[1].removeprefix("frozen at exit: "))
    assert frozen > 10_000  # numpy's, typer's and rich's objects and ours


TEARDOWN_PROBE = """
import os, sys, threading
from navsim_lb.cli import main


class TornDown:
    def __del__(self, write=os.write) -> None:  # os itself may be gone by then
        write(2, b"torn down\\n")


sys.kept = TornDown()  # freed by the interpreter's teardown (it clears sys), which a finished command skips
if sys.argv[1] == "thread":  # a thread still running: Python's exit waits for it, and tears down
    # It ends only once the main thread is done (Python's exit), however long the command takes.
    threading.Thread(target=lambda: (threading.main_thread().join(), os.write(2, b"thread done\\n"))).start()
sys.argv = ["navsim-lb", *sys.argv[2:]]
main()
"""


def test_the_script_ends_without_the_interpreters_teardown_keeping_the_exit_status(
    tmp_path: Path, one_token_split: tuple[Path, Path]
) -> None:
    """A finished command's process ends without tearing the interpreter down, with the command's exit status
    and all it printed; where a thread still runs, Python exits as usual (it waits for the thread)."""

    def probe(*arguments: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-c", TEARDOWN_PROBE, *arguments], check=False, capture_output=True, text=True
        )

    version = probe("alone", "--version")
    assert version.returncode == 0 and version.stdout.splitlines() == [f"navsim-lb {_version()}"]
    assert version.stderr == ""
    arguments = [*(str(path) for path in one_token_split), "--cache-dir", str(tmp_path / "cache")]
    scored = probe("alone", "score", *arguments, "--out", str(tmp_path / "results.csv"))
    assert scored.returncode == 0, scored.stderr
    assert "torn down" not in scored.stderr and "(PDMS v1.1)" in scored.stdout
    assert (tmp_path / "results.csv").read_text().count("\n") == 3  # the header, the token, the average
    failing = probe("alone", "score", "/no/such/split", "x.json")
    assert failing.returncode == 2 and "/no/such/split" in failing.stderr
    assert "torn down" not in failing.stderr
    waited = probe("thread", "--version")
    assert waited.returncode == 0 and waited.stdout.splitlines() == [f"navsim-lb {_version()}"]
    assert waited.stderr.splitlines() == ["thread done", "torn down"]


def _version() -> str:
    from importlib.metadata import version

    return f"{version('navsim-leaderboard')} (engine {ENGINE_VERSION})"


def test_the_command_runs_the_cycle_collector_less_often() -> None:
    """Importing the command's package raises the collector's threshold (start-up), and only the first one."""
    probe = "import gc, navsim_lb; print(gc.get_threshold(), navsim_lb.COLLECTION_ALLOCATIONS)"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["(50000,", "10,", "10)", "50000"]


WARM_SCORE_PROBE = """
import atexit, sys
from navsim_lb.cli import main


@atexit.register
def imported() -> None:
    rooms = ("navsim_lb.client", "navsim_lb.demo", "navsim_lb.openscene_cli", "server.cli", "worker.cli")
    print("other rooms imported:", [name for name in rooms if name in sys.modules])
    builders = ("scorer.pdm_closed", "scorer.planner_observation", "scorer.route")
    print("cache builders imported:", [name for name in builders if name in sys.modules])


sys.argv = ["navsim-lb", "score", *sys.argv[1:]]
main()
"""


def test_scoring_from_a_warm_cache_does_not_import_the_cache_builders(
    tmp_path: Path, one_token_split: tuple[Path, Path]
) -> None:
    """PDM-Closed and the route search only build caches: a `navsim-lb score` that finds its cache never loads
    them, nor the other rooms' commands (start-up)."""
    arguments = [*(str(path) for path in one_token_split), "--cache-dir", str(tmp_path / "cache")]
    cold, warm = (
        subprocess.run(
            [sys.executable, "-c", WARM_SCORE_PROBE, *arguments], check=False, capture_output=True, text=True
        )
        for _ in range(2)
    )
    assert cold.returncode == warm.returncode == 0, cold.stderr + warm.stderr
    builders = "['scorer.pdm_closed', 'scorer.planner_observation', 'scorer.route']"
    assert cold.stdout.splitlines()[-1] == f"cache builders imported: {builders}"  # it built the cache
    assert warm.stdout.splitlines()[-2:] == ["other rooms imported: []", "cache builders imported: []"]


LOG_REPLAY_PROBE = """
import atexit, sys
from navsim_lb.cli import main


@atexit.register
def imported() -> None:
    engines = ("scorer.reactive", "scorer.two_stage")
    print("engines imported:", sorted({name for name in sys.modules for e in engines if name.startswith(e)}))
    print("rich imported:", "rich" in sys.modules)
    print("tempfile imported:", "tempfile" in sys.modules)


sys.argv = ["navsim-lb", "score", *sys.argv[1:]]
main()
"""


def test_scoring_a_log_replay_version_does_not_import_reactive_or_two_stage_engines(
    tmp_path: Path, one_token_split: tuple[Path, Path]
) -> None:
    """Reactive traffic and the two-stage aggregation serve other versions: the default version's
    `navsim-lb score ... --out` from its cache never loads them; in a pipe it prints plain text, without rich,
    and it writes the CSV without tempfile (start-up)."""
    arguments = [*(str(path) for path in one_token_split), "--cache-dir", str(tmp_path / "cache")]
    arguments += ["--out", str(tmp_path / "results.csv")]
    cold, warm = (
        subprocess.run(
            [sys.executable, "-c", LOG_REPLAY_PROBE, *arguments], check=False, capture_output=True, text=True
        )
        for _ in range(2)
    )
    assert cold.returncode == warm.returncode == 0, cold.stderr + warm.stderr
    assert warm.stdout.splitlines()[-3:] == [
        "engines imported: []",
        "rich imported: False",
        "tempfile imported: False",
    ]
    assert "(PDMS v1.1)" in warm.stdout and f"wrote {tmp_path / 'results.csv'}" in warm.stderr
    assert (tmp_path / "results.csv").read_text().count("\n") >= 2
