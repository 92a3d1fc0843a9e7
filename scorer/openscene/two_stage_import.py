"""Import NAVSIM's two-stage data: the stage mapping, the logged frames and the synthetic scene pickles.

The mapping (`reactive_all_mapping`, from NAVSIM's split YAML such as `navhard_two_stage.yaml`, or from a
`two_stage.json`) names the stage-one tokens, imported from the OpenScene logs (`importer.import_logs`), and
the stage-two tokens, imported from the synthetic scene pickles (`synthetic.synthetic_scenes`). Outcomes go to
the importer's journal and report. `two_stage.json` is written last, and only when every token of the mapping
has its scene file: a split is never two-stage with scenes missing. A pickle's scenes are all converted and
validated before any is written, so a malformed pickle leaves nothing behind.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from scorer.files import write_atomically
from scorer.openscene.gpkg import MapFormatError
from scorer.openscene.importer import (
    JOURNAL_NAME,
    REPORT_NAME,
    ImportSettings,
    SceneFilter,
    TokenOutcome,
    build_report,
    import_logs,
    load_yaml,
    map_tables,
    scene_path,
    write_scene,
)
from scorer.openscene.scene_pickle import ScenePickleError, load_scene_pickle
from scorer.openscene.synthetic import SyntheticSceneError, synthetic_scenes
from scorer.scene import SceneFormatError, parse_scene
from scorer.two_stage.split import (
    MAPPING_FILE,
    SPLIT_FORMAT,
    SPLIT_VERSION,
    TwoStageSplit,
    TwoStageSplitError,
    parse_two_stage_split,
)

MAPPING_KEY = "reactive_all_mapping"


def read_stage_mapping(path: Path) -> TwoStageSplit:
    """Return the stage mapping of NAVSIM's split YAML (its `reactive_all_mapping`) or of a `two_stage.json`."""
    if path.suffix in (".yaml", ".yml"):
        config = load_yaml(path)
        if not isinstance(config, dict) or MAPPING_KEY not in config:
            raise TwoStageSplitError(f"{path}: no {MAPPING_KEY} (NAVSIM's two-stage split configs carry one)")
        document = {"format": SPLIT_FORMAT, "version": SPLIT_VERSION, MAPPING_KEY: config[MAPPING_KEY]}
    else:
        try:
            document = json.loads(path.read_text())
        except ValueError as error:
            raise TwoStageSplitError(f"{path}: not valid JSON: {error}") from None
    return parse_two_stage_split(document, str(path))


def import_synthetic(
    pickles_dir: Path, settings: ImportSettings, wanted: frozenset[str] | None
) -> tuple[list[TokenOutcome], list[dict[str, str]]]:
    """Write the scenes of the `*.pkl` synthetic scene pickles of `pickles_dir` that are wanted (all if None)
    and not yet written; return every wanted token's outcome and the pickles that could not be used."""
    outcomes: list[TokenOutcome] = []
    failed: list[dict[str, str]] = []
    seen: set[str] = set()
    for path in sorted(pickles_dir.glob("*.pkl")):

        def chosen(token: str) -> bool:
            return wanted is None or token in wanted

        def pending(token: str) -> bool:  # chosen and not written by an earlier run
            return chosen(token) and not scene_path(settings.out_dir, token).exists()

        try:
            scenes = synthetic_scenes(
                path,
                load_scene_pickle(path),
                lambda location: map_tables(settings.maps_dir, location),
                pending,
            )
            built = [(s.token, s.scene) for s in scenes if s.scene is not None]
            for token, scene in built:  # every scene valid before the first is written
                parse_scene(scene, f"{path} -> {token}")
        except (ScenePickleError, SyntheticSceneError, MapFormatError, SceneFormatError, OSError) as error:
            failed.append({"log": path.name, "reason": str(error)})
            continue
        for token, scene in built:
            write_scene(scene, scene_path(settings.out_dir, token))
        outcomes += [
            TokenOutcome(s.token, path.name, "present" if s.scene is None else "written", warnings=s.warnings)
            for s in scenes
            if chosen(s.token)
        ]
        seen.update(s.token for s in scenes if chosen(s.token))
    reason = f"not found in any synthetic scene pickle of {pickles_dir}" + (
        f" ({len(failed)} pickle(s) unusable)" if failed else ""
    )
    outcomes += [TokenOutcome(token, "", "skipped", reason) for token in sorted((wanted or set()) - seen)]
    return outcomes, failed


def import_two_stage(
    logs_dir: Path,
    synthetic_dir: Path,
    mapping_path: Path,
    settings: ImportSettings,
    scene_filter: SceneFilter | None = None,
    workers: int = 1,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Import a two-stage split: the mapping's stage-one tokens from the logs, its stage-two tokens from the
    synthetic pickles, then `two_stage.json` if every token has its scene; return the import report.

    A null mapping (NAVSIM's private-test config) names no tokens: the logs' scenes are those `scene_filter`
    names (all by default) and every synthetic pickle is imported; the split then stages them by token length.
    """
    split = read_stage_mapping(mapping_path)
    if split.groups is not None:
        scene_filter = SceneFilter(tokens=split.stage_one_tokens)
    report = import_logs(logs_dir, settings, scene_filter, workers, progress)
    wanted = None if split.groups is None else frozenset(split.stage_two_tokens)
    outcomes, failed = import_synthetic(synthetic_dir, settings, wanted)
    journal = settings.out_dir / JOURNAL_NAME
    with journal.open("a") as journal_file:
        journal_file.writelines(json.dumps(asdict(outcome)) + "\n" for outcome in outcomes)
    this_run = dict(report["this_run"])
    for outcome in outcomes:
        this_run[outcome.status] += 1
    report = build_report(journal, this_run, [*report["failed_logs"], *failed], logs_dir, settings)
    missing = [
        token
        for token in (*split.stage_one_tokens, *split.stage_two_tokens)
        if not scene_path(settings.out_dir, token).exists()
    ]
    report["two_stage"] = {
        "mapping": str(mapping_path),
        "groups": len(split.groups or ()),
        "stage_one_tokens": len(split.stage_one_tokens),
        "stage_two_tokens": len(split.stage_two_tokens),
        "written": not missing,
        "missing_tokens": missing,
    }
    if not missing:
        write_atomically(settings.out_dir / MAPPING_FILE, _split_document(split, mapping_path), durable=False)
    (settings.out_dir / REPORT_NAME).write_text(json.dumps(report, indent=1) + "\n")
    return report


def _split_document(split: TwoStageSplit, source: Path) -> bytes:
    """Return `two_stage.json` of a mapping (docs/scene-format.md, "Two-stage splits")."""
    mapping = (
        None
        if split.groups is None
        else [[g.original, g.previous, [list(pair) for pair in g.pairs]] for g in split.groups]
    )
    document = {
        "format": SPLIT_FORMAT,
        "version": SPLIT_VERSION,
        MAPPING_KEY: mapping,
        "stage_one_tokens": list(split.stage_one_tokens),
        "stage_two_tokens": list(split.stage_two_tokens),
        "generator": f"navsim-lb import-openscene, mapping from {source.name}",
    }
    return (json.dumps(document, indent=1) + "\n").encode()
