"""Engine subcommands of `navsim-lb`: synth, baseline, cache, score, plot, regress."""

from __future__ import annotations

import os
from collections.abc import Callable
from enum import StrEnum
from importlib.util import find_spec
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypeVar

import typer

from navsim_lb.terminal import (
    console,
    escape,
    fail,
    output,
    print_table,
    progress_bar,
    say,
    warn,
    warn_about_kernels,
)
from scorer.versions import DEFAULT_VERSION, LOG_REPLAY_VERSIONS, VERSIONS, VersionName, cached_together

if TYPE_CHECKING:
    from scorer.submission import Submission, TwoStageSubmission
    from scorer.versions import MetricVersion

Loaded = TypeVar("Loaded")
MAX_NOTES_SHOWN = 20  # per seed: what the official script would have crashed on, and what we made of it

# The pictures draw with matplotlib, an optional extra of the engine's install.
PLOT_EXTRA = "pip install 'navsim-leaderboard[plot]'"


class PictureLayout(StrEnum):
    wide = "wide"
    narrow = "narrow"


class BaselineKind(StrEnum):
    constant_velocity = "constant-velocity"
    human = "human"


def default_cache_dir(split_dir: Path) -> Path:
    """Return the cache directory of a split: $NAVSIM_LB_CACHE_DIR (default .navsim-lb/cache) / split name."""
    root = Path(os.environ.get("NAVSIM_LB_CACHE_DIR", ".navsim-lb/cache"))
    return root / Path(split_dir).resolve().name


def synth(
    out: Annotated[Path, typer.Argument(help="directory of the new split (scenes/ is created inside)")],
    scenes: Annotated[int, typer.Option(help="number of scenes")] = 200,
    seed: Annotated[int, typer.Option(help="random seed; the same seed gives the same files")] = 0,
) -> None:
    """Generate a synthetic split that exercises every metric."""
    from scorer.synth import synthesize_split

    try:
        with progress_bar("synthesising scenes", scenes) as advance:
            tokens = synthesize_split(out, scenes, seed, progress=advance)
    except FileExistsError as error:
        raise fail(f"{error}; choose an empty directory") from None
    say(f"wrote {len(tokens)} scenes to {out / 'scenes'}")


def baseline(
    kind: Annotated[BaselineKind, typer.Argument(help="which baseline agent")],
    split: Annotated[Path, typer.Argument(help="split directory")],
    out: Annotated[Path, typer.Option(help="submission JSON to write")],
) -> None:
    """Write the submission of a baseline agent (constant velocity or the recorded human) for a split."""
    from scorer.baselines import baseline_submission
    from scorer.submission import dump_submission_json

    submission = baseline_submission(split, kind.value, kind.value)
    out.write_bytes(dump_submission_json(submission))
    say(f"wrote {len(submission.seeds[0])} trajectories to {out}")


def cache(
    split: Annotated[Path, typer.Argument(help="split directory")],
    version: Annotated[
        VersionName | None,
        typer.Option(help="a metric version and those cached with it (default: v1.0, v1.1, v2.2)"),
    ] = None,
    workers: Annotated[int, typer.Option(help="processes")] = 1,
    cache_dir: Annotated[Path | None, typer.Option(help="cache directory (default: per split)")] = None,
) -> None:
    """Build the metric cache of a split (missing or stale entries only)."""
    from scorer.evaluate import build_split_cache
    from scorer.scene import SceneFormatError, scene_paths

    versions = list(LOG_REPLAY_VERSIONS) if version is None else cached_together([version])
    try:
        total = len(scene_paths(split))
    except SceneFormatError as error:
        raise fail(str(error)) from None
    warn_about_kernels()
    with progress_bar(f"caching {', '.join(versions)}", total) as advance:
        failures = build_split_cache(split, cache_dir or default_cache_dir(split), versions, workers, advance)
    for name, problem in failures.items():
        console.print(f"[red]{escape(name)}[/red]: {escape(problem)}")
    console.print(f"cached {total - len(failures)} of {total} scenes")
    if failures:
        raise typer.Exit(code=1)


def _read_submission(path: Path) -> Submission:
    """Return the submission in file `path`, or fail with what is wrong with it."""
    from scorer.submission import load_submission

    return _read(path, load_submission)


def _read_two_stage_submission(path: Path) -> TwoStageSubmission:
    """Return the two-stage submission in file `path`, or fail with what is wrong with it."""
    from scorer.submission import load_two_stage_submission

    return _read(path, load_two_stage_submission)


def _read(path: Path, loader: Callable[[bytes, str], Loaded]) -> Loaded:
    """Return what `loader` reads of file `path`, or fail with what is wrong with it."""
    from scorer.submission import SubmissionError

    try:
        return loader(path.read_bytes(), path.name)
    except OSError as error:
        raise fail(str(error)) from None
    except SubmissionError as error:
        raise fail(f"{path}: {error}") from None


def seed_csv_paths(out: Path, seeds: int) -> list[Path]:
    """Return where each seed's official two-stage CSV goes: `out` for one seed, else `<stem>.seed<i><suffix>`
    beside it (the official script scores one seed; each file is what it writes for that seed alone)."""
    if seeds == 1:
        return [out]
    return [out.with_name(f"{out.stem}.seed{index}{out.suffix}") for index in range(seeds)]


def score(
    split: Annotated[Path, typer.Argument(help="split directory")],
    submission: Annotated[Path, typer.Argument(help="submission file (JSON or NAVSIM pickle)")],
    version: Annotated[VersionName, typer.Option(help="metric version")] = DEFAULT_VERSION,
    out: Annotated[
        Path | None,
        typer.Option(help="per-token CSV with an average row (two-stage: the official CSV, one per seed)"),
    ] = None,
    cache_dir: Annotated[Path | None, typer.Option(help="cache directory (default: per split)")] = None,
    workers: Annotated[int, typer.Option(help="processes (two-stage versions)", min=1)] = 1,
) -> None:
    """Score a submission against a split and print the summary."""
    from navsim_lb.report import summary_table
    from scorer.evaluate import score_tokens
    from scorer.scene import SceneFormatError, scene_paths
    from scorer.submission import validate_submission

    metric_version = VERSIONS[version]
    if metric_version.two_stage:
        _score_two_stage(
            split, submission, metric_version, out, cache_dir or default_cache_dir(split), workers
        )
        return
    if workers > 1:
        raise fail(f"--workers: {version} scores in one process; several are for the two-stage versions")
    try:
        tokens = list(scene_paths(split))
    except (SceneFormatError, OSError) as error:
        raise fail(str(error)) from None
    loaded = _read_submission(submission)
    for problem in validate_submission(loaded, tokens):
        warn(str(problem))
    warn_about_kernels()
    results = []
    with progress_bar(f"scoring {version}", len(tokens) * len(loaded.seeds)) as advance:
        for index, predictions in enumerate(loaded.seeds):
            seed = index if len(loaded.seeds) > 1 else None
            results += score_tokens(
                split, cache_dir or default_cache_dir(split), predictions, version, tokens, seed, advance
            )
    if out is not None:
        from scorer.result_csv import write_results_csv

        write_results_csv(results, metric_version, out)
        say(f"wrote {out}")
    print_table(summary_table(results, metric_version, f"{loaded.metadata.method} on {split.name}"))


def _score_two_stage(
    split: Path, submission: Path, version: MetricVersion, out: Path | None, cache_dir: Path, workers: int
) -> None:
    """Score a two-stage submission on a two-stage split: coverage warnings per stage, the official CSV of each
    seed, and the summary with what the official script would have crashed on."""
    from navsim_lb.report import two_stage_summary_table
    from scorer.scene import SceneFormatError
    from scorer.submission import two_stage_coverage_problems
    from scorer.two_stage.result_csv import write_two_stage_csv
    from scorer.two_stage.score import score_two_stage
    from scorer.two_stage.split import MAPPING_FILE, TwoStageSplitError, load_two_stage_split

    if not (split / MAPPING_FILE).is_file():
        raise fail(
            f"{split}: no {MAPPING_FILE}, so not a two-stage split; {version.name} scores NAVSIM's two stages "
            "over a split's stage mapping (a one-stage split takes a one-stage version, e.g. v2.2)"
        )
    try:
        stages = load_two_stage_split(split)
    except (TwoStageSplitError, SceneFormatError, OSError) as error:
        raise fail(str(error)) from None
    loaded = _read_two_stage_submission(submission)
    for problem in two_stage_coverage_problems(
        [list(seed) for seed in loaded.first_stage],
        [list(seed) for seed in loaded.second_stage],
        stages.stage_one_tokens,
        stages.stage_two_tokens,
    ):
        warn(str(problem))
    warn_about_kernels()
    # Every token any seed names is scored for every seed (as the one-stage scoring counts).
    total = len(set().union(*loaded.first_stage, *loaded.second_stage)) * len(loaded.first_stage)
    with progress_bar(f"scoring {version.name}", total) as advance:
        results = score_two_stage(split, cache_dir, loaded, version.name, advance, workers)
    for index, result in enumerate(results):
        seed = f"seed {index}: " if len(results) > 1 else ""
        for note in result.notes[:MAX_NOTES_SHOWN]:
            warn(seed + note)
        if len(result.notes) > MAX_NOTES_SHOWN:
            warn(f"{seed}{len(result.notes) - MAX_NOTES_SHOWN} more note(s) not shown")
    if out is not None:
        for result, path in zip(results, seed_csv_paths(out, len(results)), strict=True):
            write_two_stage_csv(result, path)
            say(f"wrote {path}")
    title = f"{loaded.metadata.method} on {split.name}"
    print_table(two_stage_summary_table(results, version, title))


def plot(
    split: Annotated[Path, typer.Argument(help="split directory")],
    submission: Annotated[Path, typer.Argument(help="submission file (JSON or NAVSIM pickle)")],
    token: Annotated[str, typer.Argument(help="the scene token to draw")],
    out: Annotated[Path, typer.Option(help="picture to write: .png or .svg")],
    version: Annotated[VersionName, typer.Option(help="metric version")] = DEFAULT_VERSION,
    seed: Annotated[int, typer.Option(help="seed of a multi-seed submission")] = 0,
    cache_dir: Annotated[Path | None, typer.Option(help="cache directory (default: per split)")] = None,
    layout: Annotated[
        PictureLayout, typer.Option(help="wide: legend beside the map; narrow: for a phone, legend below")
    ] = PictureLayout.wide,
) -> None:
    """Draw why a token scored what it did: map, objects, trajectories, the first infraction of each kind;
    under a reactive version the vehicles as simulated, and on a two-stage split (a two-stage version) a
    stage-one token's synthetic starts with their weights."""
    if find_spec("matplotlib") is None:  # finding the module does not import it: start-up stays fast
        raise fail(f"`navsim-lb plot` draws with matplotlib, not installed here: {PLOT_EXTRA}")
    from scorer.evaluate import TokenError
    from scorer.explain import explain_split_token
    from scorer.picture import render
    from scorer.scene import SceneFormatError

    image_format = out.suffix.lower().removeprefix(".")
    if image_format not in ("png", "svg"):
        raise fail(f"{out}: the picture must end in .png or .svg")
    from scorer.two_stage.score import predictions_per_seed

    seeds = _read(submission, lambda content, name: predictions_per_seed(content, name, version))
    if not 0 <= seed < len(seeds):
        from server.numbers import counted

        raise fail(f"{submission} has {counted(len(seeds), 'seed')}; --seed {seed} does not exist")
    if token not in seeds[seed]:
        raise fail(f"{submission} has no prediction for token {token}")
    warn_about_kernels()
    try:
        explanation = explain_split_token(
            split, cache_dir or default_cache_dir(split), token, seeds[seed][token], version
        )
    except (TokenError, SceneFormatError) as error:
        raise fail(str(error)) from None
    out.write_bytes(render(explanation, image_format, layout.value))
    score = explanation.metrics["score"]
    label = VERSIONS[explanation.version].score_label
    console.print(f"{token}: {label} {version} {100 * score:.1f}; wrote {out}")
    if explanation.synthetic_starts is not None:
        starts = explanation.synthetic_starts
        for synthetic, weight in zip(starts.tokens, starts.weights.weight, strict=True):
            console.print(f"  synthetic start {synthetic}: weight {weight:.4f}")
    for infraction in explanation.infractions:
        involved = (
            f" with {infraction.object_type} {infraction.object_token}" if infraction.object_token else ""
        )
        console.print(f"  {infraction.kind} at {infraction.time_s:.1f} s{involved}")


def regress(
    update: Annotated[bool, typer.Option(help="rewrite the golden files instead of comparing")] = False,
) -> None:
    """Compare the engine with the versioned golden results of the regression split (fails above 1e-9)."""
    from rich.table import Table

    from scorer.regression import run_regression

    warn_about_kernels()
    changes = run_regression(update=update, progress=progress_bar)
    if update:
        console.print("golden results rewritten")
        return
    if not changes:
        console.print("[green]no change[/green] against the golden results")
        return
    table = Table(title="changed results")
    for column in ("version", "family", "token", "metric", "old", "new"):
        table.add_column(column)
    for change in changes:
        table.add_row(*(str(value) for value in change))
    output.print(table)
    raise typer.Exit(code=1)


def register(app: typer.Typer) -> None:
    """Add the engine's subcommands to `app`."""
    for command in (synth, baseline, cache, score, plot, regress):
        app.command()(command)
