"""`navsim-lb import-openscene` and `navsim-lb curate`: build hidden splits from organiser data."""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import Annotated

import typer

from navsim_lb.engine_cli import default_cache_dir
from navsim_lb.terminal import console, escape, fail, output, progress_bar
from scorer.versions import DEFAULT_VERSION, VersionName

SHOWN_REASONS = 10


def import_openscene(
    out: Annotated[
        Path, typer.Argument(help="split directory to fill (scenes/ and the import report go inside)")
    ],
    logs: Annotated[Path, typer.Option(help="directory of OpenScene log pickles (<log_name>.pkl)")],
    maps: Annotated[
        Path, typer.Option(help="nuPlan map root (nuplan-maps-v1.0.json, <location>/<version>/map.gpkg)")
    ],
    tokens: Annotated[
        Path | None,
        typer.Option(help="scene filter: NAVSIM's YAML (tokens, log_names or both) or one token per line"),
    ] = None,
    workers: Annotated[int, typer.Option(help="processes (one log per task)")] = max(1, os.cpu_count() or 1),
    frame_interval: Annotated[
        int, typer.Option(help="frames between scene windows (navtest/navtrain: 1)")
    ] = 1,
    require_route: Annotated[bool, typer.Option(help="skip scenes whose current frame has no route")] = True,
    check_commands: Annotated[
        bool, typer.Option(help="recompute stored driving commands and report mismatches")
    ] = True,
    future_frames: Annotated[
        int,
        typer.Option(
            help="future frames a logged scene needs (NAVSIM's num_future_frames: navtest 10, navhard 8); "
            "a window the log ends before 10 holds its last frame",
            min=8,
            max=10,
        ),
    ] = 10,
    stage_mapping: Annotated[
        Path | None,
        typer.Option(
            help="two-stage split: NAVSIM's split YAML (its reactive_all_mapping) or a two_stage.json; "
            "the logs give the stage-one tokens, --synthetic the stage-two ones"
        ),
    ] = None,
    synthetic: Annotated[
        Path | None,
        typer.Option(help="directory of NAVSIM synthetic scene pickles (Scene.save_to_disk, <token>.pkl)"),
    ] = None,
) -> None:
    """Import OpenScene logs and nuPlan maps into scene files; resumable, with a report of skipped tokens.

    With --stage-mapping and --synthetic, a two-stage split: the synthetic scenes too, and two_stage.json."""
    from scorer.openscene.importer import REPORT_NAME, ImportSettings, import_logs, read_scene_filter
    from scorer.openscene.two_stage_import import import_two_stage

    for directory in (logs, maps, synthetic):
        if directory is not None and not directory.is_dir():
            raise fail(f"{directory}: not a directory")
    if (stage_mapping is None) != (synthetic is None):
        raise fail("a two-stage import needs both --stage-mapping and --synthetic")
    if frame_interval < 1:
        raise fail(f"--frame-interval must be at least 1, got {frame_interval}")
    try:
        wanted = None if tokens is None else read_scene_filter(tokens)
    except (OSError, ValueError) as error:
        raise fail(str(error)) from None
    settings = ImportSettings(maps, out, frame_interval, require_route, check_commands, future_frames)
    total = sum(1 for path in logs.iterdir() if path.suffix == ".pkl")
    with progress_bar("importing logs", total) as advance:
        if stage_mapping is None or synthetic is None:
            report = import_logs(logs, settings, wanted, workers, advance)
        else:
            try:
                report = import_two_stage(logs, synthetic, stage_mapping, settings, wanted, workers, advance)
            except (OSError, ValueError) as error:
                raise fail(str(error)) from None
    run = report["this_run"]
    console.print(
        f"{run['written']} scenes written, {run['present']} already present, {run['skipped']} skipped; "
        f"{report['scenes']} scenes in {out / 'scenes'}"
    )
    for failure in report["failed_logs"]:
        console.print(f"[red]{escape(failure['log'])}[/red]: {escape(failure['reason'])}")
    reasons = Counter(entry["reason"] for entry in report["skipped"])
    if reasons:
        from rich.table import Table

        table = Table(title="skipped tokens by reason")
        table.add_column("tokens", justify="right")
        table.add_column("reason")
        for reason, count in reasons.most_common(SHOWN_REASONS):
            table.add_row(str(count), escape(reason))
        output.print(table)
    if report["command_mismatches"]:
        console.print(
            f"[yellow]{len(report['command_mismatches'])} stored driving commands differ from the route's[/yellow]"
        )
    two_stage = report.get("two_stage")
    if two_stage is not None and two_stage["written"]:
        console.print(f"two-stage split: {two_stage['groups']} groups in {out / 'two_stage.json'}")
    elif two_stage is not None:
        missing = two_stage["missing_tokens"]
        console.print(
            f"[red]two_stage.json not written: {len(missing)} token(s) of the mapping have no scene[/red] "
            f"({escape(', '.join(missing[:SHOWN_REASONS]))}{', ...' if len(missing) > SHOWN_REASONS else ''})"
        )
    console.print(f"report: {out / REPORT_NAME}")
    if two_stage is not None and not two_stage["written"]:
        raise typer.Exit(code=1)


def curate(
    split: Annotated[Path, typer.Argument(help="split directory to curate")],
    out: Annotated[Path, typer.Option(help="directory of the curated split")],
    version: Annotated[VersionName, typer.Option(help="metric version")] = DEFAULT_VERSION,
    threshold: Annotated[float, typer.Option(help="PDMS threshold for both agents")] = 0.8,
    cache_dir: Annotated[Path | None, typer.Option(help="cache directory (default: per split)")] = None,
) -> None:
    """Drop scenes the constant-velocity agent solves (PDMS > 0.8) or the human fails (< 0.8); print Table 3."""
    from rich.table import Table

    from scorer.openscene.curation import AGENTS, curate_split, curation_table
    from scorer.scene import SceneFormatError, scene_paths

    try:
        total = len(scene_paths(split)) * len(AGENTS)
        with progress_bar(f"scoring baselines ({version})", total) as advance:
            result = curate_split(
                split, out, cache_dir or default_cache_dir(split), version, threshold, advance
            )
    except (SceneFormatError, ValueError) as error:
        raise fail(str(error)) from None
    rows = curation_table(result)
    table = Table(title=f"{split.name}: before and after curation ({version}, threshold {threshold})")
    for column in rows[0]:
        table.add_column(column)
    for row in rows[1:]:
        table.add_row(*row)
    output.print(table)
    console.print(
        f"kept {len(result.kept)} of {len(result.kept) + len(result.dropped)} scenes in {out / 'scenes'}"
    )


def register(app: typer.Typer) -> None:
    """Add `import-openscene` and `curate` to `app`."""
    app.command("import-openscene")(import_openscene)
    app.command()(curate)
