"""Import OpenScene logs into a split directory: one scene file per token, parallel and resumable.

Each log is one task. A token whose scene file exists is left alone, so an interrupted import goes
on where it stopped; scene files appear atomically (written aside, validated, renamed). Every
outcome is appended to `import-journal.jsonl` as it arrives, and `import-report.json` (skipped
tokens and why, driving-command mismatches, conversion warnings) is rebuilt from that journal.
"""

from __future__ import annotations

import gzip
import json
import re
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

from scorer.files import write_atomically
from scorer.openscene.excerpt import Excerpt, build_excerpt, excerpt_to_json
from scorer.openscene.frames import (
    CURRENT_INDEX,
    FRAME_INTERVAL_S,
    NUM_FRAMES,
    NUM_FUTURE_FRAMES,
    FrameError,
    convert_frame,
    ego_pose,
    padded_future,
    route_roadblocks,
    scene_windows,
    vehicle_centres,
    window_problem,
)
from scorer.openscene.gpkg import MapFormatError, MapTables, gpkg_path, load_map_tables, map_location
from scorer.openscene.log_pickle import LogFormatError, load_log
from scorer.openscene.navigation import navigation_command
from scorer.scene import SCENE_FORMAT, SCENE_VERSION, SceneFormatError, parse_scene

JOURNAL_NAME = "import-journal.jsonl"
REPORT_NAME = "import-report.json"
REPORT_FORMAT = "navsim-lb/import-report"
TOKEN_PATTERN = re.compile(r"[0-9a-f]{16}")
UNKNOWN_COMMAND = [0, 0, 0, 1]
MAP_CACHE_SIZE = 2  # whole maps are large; logs of one city usually come together


@dataclass(frozen=True)
class ImportSettings:
    """Where maps live, where scenes go, and how windows are cut (NAVSIM's SceneFilter)."""

    maps_dir: Path
    out_dir: Path
    frame_interval: int = 1  # navtest/navtrain slide by one frame
    require_route: bool = True  # SceneFilter.has_route; a scene without route cannot be cached by the devkit
    check_commands: bool = True  # recompute the current frame's stored command and report mismatches
    # SceneFilter.num_future_frames: 10 for navtest, 8 for navhard (v2 observes 8). A window is cut with up to
    # 10; one the log ends after 8 or 9 holds its last frame to the format's 10 (a warning says so).
    future_frames: int = NUM_FUTURE_FRAMES


@dataclass(frozen=True)
class TokenOutcome:
    """What happened to one token: written, already present, or skipped (with the reason)."""

    token: str
    log: str
    status: str  # "written" | "present" | "skipped"
    reason: str | None = None
    warnings: tuple[str, ...] = ()
    stored_command: list[int] | None = None  # current frame, as in the log
    computed_command: list[int] | None = None  # current frame, from the route (when checked)
    computed_frames: int = 0  # frames whose missing command was computed


@dataclass(frozen=True)
class LogOutcome:
    """The outcomes of one log, every frame token seen in it, or why it could not be read."""

    log: str
    tokens: list[TokenOutcome] = field(default_factory=list)
    seen: list[str] = field(default_factory=list)
    error: str | None = None


def scene_path(out_dir: Path, token: str) -> Path:
    """Return where the importer writes a token's scene file."""
    return out_dir / "scenes" / f"{token}.json.gz"


@dataclass(frozen=True)
class SceneFilter:
    """Which scenes to import, as NAVSIM's scene filter says: tokens, logs, or both (None: no restriction)."""

    tokens: tuple[str, ...] | None = None
    log_names: tuple[str, ...] | None = None


def _names(document: Mapping[str, Any], key: str, path: Path) -> tuple[str, ...] | None:
    values = document.get(key)
    if values is None:
        return None
    if not isinstance(values, list) or not all(isinstance(value, str) for value in values):
        raise ValueError(f"{path}: {key} must be a list of names")
    return tuple(dict.fromkeys(values))


def _checked_tokens(tokens: Sequence[str], where: Callable[[int], str]) -> tuple[str, ...]:
    for index, token in enumerate(tokens):
        if not TOKEN_PATTERN.fullmatch(token):
            raise ValueError(f"{where(index)}: {token!r} is not a token (16 lowercase hex characters)")
    return tuple(dict.fromkeys(tokens))


def load_yaml(path: Path) -> Any:
    """Return the content of one of NAVSIM's config files (safe YAML: data only)."""
    import yaml  # only organisers importing logs need it

    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise ValueError(f"{path}: not YAML ({error})") from None


def read_scene_filter(path: Path) -> SceneFilter:
    """Return the scene filter of a file: NAVSIM's scene-filter YAML (`.yaml`/`.yml`: its `tokens`, its
    `log_names`, or both; the other keys are NAVSIM's own) or a list of tokens, one per line (`#` comments)."""
    text = path.read_text()
    if path.suffix in (".yaml", ".yml"):
        document = load_yaml(path)
        if not isinstance(document, dict):
            raise ValueError(f"{path}: expected a mapping with tokens and/or log_names")
        tokens, log_names = _names(document, "tokens", path), _names(document, "log_names", path)
        if tokens is None and log_names is None:
            raise ValueError(f"{path}: neither tokens nor log_names is given")
        if tokens is not None:
            tokens = _checked_tokens(tokens, lambda index: f"{path}: tokens[{index}]")
        return SceneFilter(tokens, log_names)
    lines = [
        (number, line.split("#", 1)[0].strip()) for number, line in enumerate(text.splitlines(), start=1)
    ]
    lines = [(number, token) for number, token in lines if token]
    tokens = _checked_tokens([token for _, token in lines], lambda index: f"{path}:{lines[index][0]}")
    return SceneFilter(tokens=tokens)


_wanted_tokens: frozenset[str] | None = None


def _set_wanted_tokens(tokens: frozenset[str] | None) -> None:
    """Pool initializer: hand the token list to a worker once, not with every task."""
    global _wanted_tokens
    _wanted_tokens = tokens


@lru_cache(maxsize=MAP_CACHE_SIZE)
def map_tables(maps_dir: Path, location: str) -> MapTables:
    """Return the tables of a map location, the last few kept loaded."""
    return load_map_tables(gpkg_path(maps_dir, location), location)


def import_log(log_path: Path, settings: ImportSettings) -> LogOutcome:
    """Write the scenes of one log that are wanted and not yet written; return every token's outcome."""
    try:
        frames = load_log(log_path)
    except (LogFormatError, OSError) as error:
        return LogOutcome(log=log_path.stem, error=str(error))
    log = _LogScenes(log_path.stem, frames, settings)
    outcomes = [
        log.import_token(token, start, problem) for token, start, problem in log.candidates(_wanted_tokens)
    ]
    return LogOutcome(log=log_path.stem, tokens=outcomes, seen=log.tokens)


class _LogScenes:
    """One loaded log: frames are converted, and commands computed, once per frame for all its windows."""

    def __init__(self, name: str, frames: list[dict[str, Any]], settings: ImportSettings) -> None:
        self.name = name
        self.frames = frames
        self.settings = settings
        self.tokens = [str(frame.get("token")) for frame in frames]
        self._converted: dict[int, dict[str, Any]] = {}
        self._computed_commands: dict[int, list[int]] = {}

    def candidates(self, wanted: frozenset[str] | None) -> Iterator[tuple[str, int, str | None]]:
        """Yield (token, window start, problem) for the windows to import."""
        if wanted is None:
            for token, start in scene_windows(
                self.frames, self.settings.frame_interval, self.settings.future_frames
            ):
                yield token, start, None
            return
        for index, token in enumerate(self.tokens):
            if token in wanted:
                yield (
                    token,
                    index - CURRENT_INDEX,
                    window_problem(
                        self.frames, index, self.settings.frame_interval, self.settings.future_frames
                    ),
                )

    def import_token(self, token: str, start: int, problem: str | None) -> TokenOutcome:
        if problem is not None:
            return TokenOutcome(token, self.name, "skipped", problem)
        out_path = scene_path(self.settings.out_dir, token)
        if out_path.exists() or out_path.with_suffix("").exists():
            return TokenOutcome(token, self.name, "present")
        try:
            return self._write_scene(token, start, out_path)
        except (FrameError, MapFormatError, SceneFormatError) as error:
            return TokenOutcome(token, self.name, "skipped", f"{type(error).__name__}: {error}")

    def _write_scene(self, token: str, start: int, out_path: Path) -> TokenOutcome:
        current_index = start + CURRENT_INDEX
        current = self.frames[current_index]
        route = route_roadblocks(current)
        if self.settings.require_route and not route:
            return TokenOutcome(
                token, self.name, "skipped", "no route at the current frame (roadblock_ids is empty)"
            )
        location = map_location(str(current.get("map_location")))
        pose = ego_pose(current)
        end = min(start + NUM_FRAMES, len(self.frames))
        frames = [dict(self._convert(index)) for index in range(start, end)]
        vehicles = vehicle_centres(frames[CURRENT_INDEX]["objects"])
        excerpt = build_excerpt(map_tables(self.settings.maps_dir, location), pose, route, vehicles)
        stored_command = frames[CURRENT_INDEX]["driving_command"]
        check = self.settings.check_commands or stored_command is None
        computed_command = self._command(current_index, excerpt) if check else None
        computed_frames = 0
        for offset, frame in enumerate(frames):
            if frame["driving_command"] is None:
                frame["driving_command"] = self._command(
                    start + offset, excerpt if offset == CURRENT_INDEX else None
                )
                computed_frames += 1
        future, padding = padded_future(frames[CURRENT_INDEX + 1 :])
        frames = frames[: CURRENT_INDEX + 1] + future
        scene = {
            "format": SCENE_FORMAT,
            "version": SCENE_VERSION,
            "token": token,
            "log_name": str(current.get("log_name") or self.name),
            "map_name": location,
            "frame_interval_s": FRAME_INTERVAL_S,
            "current_index": CURRENT_INDEX,
            "frames": frames,
            "map": excerpt_to_json(excerpt.map),
        }
        write_scene(scene, out_path)
        return TokenOutcome(
            token,
            self.name,
            "written",
            warnings=(*excerpt.warnings, *padding),
            stored_command=stored_command,
            computed_command=computed_command,
            computed_frames=computed_frames,
        )

    def _convert(self, index: int) -> dict[str, Any]:
        if index not in self._converted:
            self._converted[index] = convert_frame(self.frames[index])
        return self._converted[index]

    def _command(self, index: int, excerpt: Excerpt | None) -> list[int]:
        """Return the navigation command computed for a frame from its own pose, route and map neighbourhood."""
        if index not in self._computed_commands:
            frame = self.frames[index]
            route = route_roadblocks(frame)
            pose = ego_pose(frame)
            if not route:
                command = list(UNKNOWN_COMMAND)
            else:
                location = map_location(str(frame.get("map_location")))
                if excerpt is None:
                    excerpt = build_excerpt(map_tables(self.settings.maps_dir, location), pose, route)
                command = navigation_command(excerpt.map, pose, route)
            self._computed_commands[index] = command
        return self._computed_commands[index]


def write_scene(scene: dict[str, Any], out_path: Path) -> None:
    """Validate the scene as the reader will, then write it compressed (atomically)."""
    parse_scene(scene, str(out_path))
    data = gzip.compress(json.dumps(scene, separators=(",", ":"), allow_nan=False).encode(), mtime=0)
    write_atomically(out_path, data, durable=False)  # an import is resumable: a lost scene is written again


def import_logs(
    logs_dir: Path,
    settings: ImportSettings,
    scene_filter: SceneFilter | None = None,
    workers: int = 1,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Import the `*.pkl` logs of `logs_dir` the filter names (every one by default), keeping the scenes it names;
    return the import report (also written to the output directory)."""
    scene_filter = scene_filter or SceneFilter()
    log_paths = sorted(
        path
        for path in Path(logs_dir).iterdir()
        if path.suffix == ".pkl" and (scene_filter.log_names is None or path.stem in scene_filter.log_names)
    )
    wanted = None if scene_filter.tokens is None else frozenset(scene_filter.tokens)
    settings.out_dir.mkdir(parents=True, exist_ok=True)
    journal = settings.out_dir / JOURNAL_NAME
    seen: set[str] = set()
    this_run = {"written": 0, "present": 0, "skipped": 0}
    present = {path.stem for path in log_paths}
    failed_logs = [
        {"log": name, "reason": f"named by the scene filter but not in {logs_dir}"}
        for name in scene_filter.log_names or ()
        if name not in present
    ]
    with journal.open("a") as journal_file:
        for outcome in _run(log_paths, settings, wanted, workers):
            if outcome.error is not None:
                failed_logs.append({"log": outcome.log, "reason": outcome.error})
            seen.update(outcome.seen)
            for token_outcome in outcome.tokens:
                this_run[token_outcome.status] += 1
                journal_file.write(json.dumps(asdict(token_outcome)) + "\n")
            journal_file.flush()
            if progress is not None:
                progress(1)
        for token in sorted((wanted or frozenset()) - seen):
            searched = "the logs the filter names" if scene_filter.log_names is not None else "any log"
            reason = f"not found in {searched} of {logs_dir}" + (
                f" ({len(failed_logs)} log(s) unreadable)" if failed_logs else ""
            )
            journal_file.write(json.dumps(asdict(TokenOutcome(token, "", "skipped", reason))) + "\n")
            this_run["skipped"] += 1
    report = build_report(journal, this_run, failed_logs, logs_dir, settings)
    (settings.out_dir / REPORT_NAME).write_text(json.dumps(report, indent=1) + "\n")
    return report


def _run(
    log_paths: Sequence[Path], settings: ImportSettings, wanted: frozenset[str] | None, workers: int
) -> Iterator[LogOutcome]:
    if workers <= 1:
        _set_wanted_tokens(wanted)
        try:
            yield from (import_log(path, settings) for path in log_paths)
        finally:
            _set_wanted_tokens(None)
        return
    with ProcessPoolExecutor(
        max_workers=workers, initializer=_set_wanted_tokens, initargs=(wanted,)
    ) as executor:
        futures: list[Future[LogOutcome]] = [
            executor.submit(import_log, path, settings) for path in log_paths
        ]
        for future in as_completed(futures):
            yield future.result()


def build_report(
    journal: Path,
    this_run: Mapping[str, int],
    failed_logs: Sequence[Mapping[str, str]],
    logs_dir: Path,
    settings: ImportSettings,
) -> dict[str, Any]:
    """Return the report of the split's state: the latest outcome per token over every run in the journal."""
    latest: dict[str, dict[str, Any]] = {}
    for line in journal.read_text().splitlines():
        record = json.loads(line)
        previous = latest.get(record["token"])
        # "present" only confirms an earlier run's record; it replaces nothing it knows less about.
        if record["status"] == "present" and previous is not None and previous["status"] == "written":
            continue
        latest[record["token"]] = record
    records = [latest[token] for token in sorted(latest)]
    on_disk = [r for r in records if r["status"] in ("written", "present")]
    return {
        "format": REPORT_FORMAT,
        "version": 1,
        "logs_dir": str(logs_dir),
        "maps_dir": str(settings.maps_dir),
        "frame_interval": settings.frame_interval,
        "require_route": settings.require_route,
        "this_run": dict(this_run),
        "failed_logs": list(failed_logs),
        "scenes": len(on_disk),
        "skipped": [
            {"token": r["token"], "log": r["log"], "reason": r["reason"]}
            for r in records
            if r["status"] == "skipped"
        ],
        "command_mismatches": [
            {
                "token": r["token"],
                "log": r["log"],
                "stored": r["stored_command"],
                "computed": r["computed_command"],
            }
            for r in on_disk
            if r["stored_command"] is not None
            and r["computed_command"] is not None
            and r["stored_command"] != r["computed_command"]
        ],
        "computed_commands": [
            {"token": r["token"], "log": r["log"], "frames": r["computed_frames"]}
            for r in on_disk
            if r["computed_frames"]
        ],
        "warnings": [
            {"token": r["token"], "log": r["log"], "message": w} for r in on_disk for w in r["warnings"]
        ],
    }
