"""Client commands of `navsim-lb`: `submit` a file to a server with upload and scoring progress, and
`validate` one locally with the server's own checks (the same verdict, nothing sent)."""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import IO, TYPE_CHECKING, Annotated, Any, cast

import typer

from navsim_lb.terminal import console, escape, fail

if TYPE_CHECKING:  # httpx takes a third of `navsim-lb --help`, rich.progress a tenth of `score`'s start-up:
    # the commands that need them import them when they run
    import httpx
    from rich.progress import Progress
    from rich.table import Table

API_PREFIX = "/api/v1"
DEFAULT_SERVER = "http://127.0.0.1:8000"
FINAL_STATUSES = ("scored", "failed", "cancelled")
MAX_LISTED_PROBLEMS = 30
TIMEOUT_S, CONNECT_TIMEOUT_S = 60.0, 10.0


class ReadProgress:
    """A binary file whose reads advance a callback by the bytes read (httpx streams multipart from it)."""

    def __init__(self, handle: IO[bytes], advance: Callable[[int], None]) -> None:
        self._handle = handle
        self._advance = advance

    def read(self, size: int = -1) -> bytes:
        chunk = self._handle.read(size)
        self._advance(len(chunk))
        return chunk

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._handle.seek(offset, whence)

    def tell(self) -> int:
        return self._handle.tell()

    def fileno(self) -> int:
        # httpx measures the file through its descriptor, so the upload has a Content-Length.
        return self._handle.fileno()


def problem_lines(problems: list[dict[str, Any]]) -> list[str]:
    """Return one line per problem (token, field, message), the first MAX_LISTED_PROBLEMS of them."""
    lines = []
    for problem in problems[:MAX_LISTED_PROBLEMS]:
        token = f"token {problem['token']}" if problem.get("token") else None
        where = ", ".join(part for part in (problem.get("field"), token) if part)
        lines.append(f"  - {where}: {problem['message']}" if where else f"  - {problem['message']}")
    if len(problems) > MAX_LISTED_PROBLEMS:
        lines.append(f"  … and {len(problems) - MAX_LISTED_PROBLEMS} more")
    return lines


def refusal_lines(response: httpx.Response) -> list[str]:
    """Return the server's explanation of a refused request: its detail, then one line per problem."""
    try:
        body = response.json()
    except ValueError:
        return [f"HTTP {response.status_code}: {response.text[:500]}"]
    detail = body.get("detail") if isinstance(body, dict) else body
    lines = []
    if isinstance(detail, list):  # FastAPI's own request validation: a list of {loc, msg}
        lines += [f"{'.'.join(map(str, item.get('loc', [])))}: {item.get('msg')}" for item in detail]
    else:
        lines.append(str(detail))
    lines += problem_lines(body.get("problems", []) if isinstance(body, dict) else [])
    if isinstance(body, dict) and body.get("submission_id") is not None:
        lines.append(f"  (submission {body['submission_id']})")
    # A quota's detail states when it resets; the header would say it a second time.
    if response.headers.get("Retry-After") and not (isinstance(body, dict) and "resets_at" in body):
        lines.append(f"  retry after {response.headers['Retry-After']} s")
    return lines


def _refused(response: httpx.Response) -> typer.Exit:
    lines = [f"the server refused the request (HTTP {response.status_code}):", *refusal_lines(response)]
    return fail("\n".join(lines))


def upload(
    client: httpx.Client, file: Path, fields: dict[str, str], progress: Progress | None = None
) -> dict[str, Any]:
    """POST a submission file; return the server's 202 body, or raise typer.Exit listing its problems."""
    size = file.stat().st_size
    task = progress.add_task(f"uploading {file.name}", total=size) if progress is not None else None

    def advance(count: int) -> None:
        if progress is not None and task is not None:
            progress.update(task, advance=count)

    with file.open("rb") as handle:
        response = client.post(
            f"{API_PREFIX}/submissions",
            # httpx reads it as it reads a file.
            files={
                "file": (
                    file.name,
                    cast(IO[bytes], ReadProgress(handle, advance)),
                    "application/octet-stream",
                )
            },
            data=fields,
            # One key per invocation: a retried request cannot create a second submission.
            headers={"Idempotency-Key": uuid.uuid4().hex},
        )
    if response.status_code != 202:
        raise _refused(response)
    return response.json()


def wait_until_done(client: httpx.Client, submission_id: int, poll_s: float = 1.0) -> dict[str, Any]:
    """Poll a submission, with a progress bar, until it is scored, failed or cancelled; return that state."""
    from rich.progress import BarColumn, Progress, TextColumn

    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"))
    with Progress(*columns, console=console.rich) as progress:
        task = progress.add_task("queued", total=100)
        while True:
            response = client.get(f"{API_PREFIX}/submissions/{submission_id}")
            if response.status_code != 200:
                raise _refused(response)
            state = response.json()
            progress.update(task, completed=state["progress"], description=state["status"])
            if state["status"] in FINAL_STATUSES:
                return state
            time.sleep(poll_s)


def results_table(state: dict[str, Any]) -> Table:
    """Return a table of a scored submission: the score (PDMS or EPDMS), 95% interval and failed tokens per
    version and subset, in % as the pages show them."""
    from rich.table import Table

    from scorer.versions import VERSIONS, VersionName  # plain data: no engine import
    from server.numbers import percent

    table = Table(title=f"submission {state['id']}: {escape(state['method'])}", caption="scores in %")
    for column in ("version", "subset", "score", "95% CI", "seeds", "failed tokens"):
        table.add_column(column, justify="left" if column in ("version", "subset") else "right")
    for version, subsets in sorted(state["results"].items()):
        for subset, result in subsets.items():
            low, high = result["ci95"]
            table.add_row(
                f"{VERSIONS[VersionName(version)].score_label} {version}",
                subset,
                percent(result["score"]),
                f"{percent(low)}–{percent(high)}",
                str(result["seeds"]["count"]),
                str(result["failed_tokens"]),
            )
    return table


def submit(
    file: Annotated[Path, typer.Argument(help="submission: navsim-lb JSON or NAVSIM pickle (xz or not)")],
    server: Annotated[str, typer.Option(envvar="NAVSIM_LB_SERVER", help="server URL")] = DEFAULT_SERVER,
    token: Annotated[str, typer.Option(envvar="NAVSIM_LB_TOKEN", help="your team's API token")] = "",
    wait: Annotated[bool, typer.Option("--wait", help="follow scoring until it ends")] = False,
    phase: Annotated[str | None, typer.Option(help="phase (default: the open one)")] = None,
    method: Annotated[str | None, typer.Option(help="method name shown on the leaderboard")] = None,
) -> None:
    """Upload a submission (prints its id on stdout); with --wait, follow scoring and print the results."""
    if not token:
        raise fail("give your team's API token with --token or NAVSIM_LB_TOKEN")
    if not file.is_file():
        raise fail(f"{file}: no such file")
    fields = {name: value for name, value in (("phase", phase), ("method", method)) if value}
    import httpx
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TransferSpeedColumn

    headers = {"Authorization": f"Bearer {token}"}
    # Retries cover failed connections only; the POST carries an idempotency key anyway.
    transport = httpx.HTTPTransport(retries=2)
    timeout = httpx.Timeout(TIMEOUT_S, connect=CONNECT_TIMEOUT_S)
    try:
        with httpx.Client(base_url=server, headers=headers, timeout=timeout, transport=transport) as client:
            columns = (TextColumn("{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn())
            with Progress(*columns, console=console.rich) as progress:
                accepted = upload(client, file, fields, progress)
            replay = " (an earlier request with this key created it)" if accepted["replayed"] else ""
            console.print(
                escape(f"submission {accepted['id']} {accepted['status']}{replay}: {accepted['url']}")
            )
            print(accepted["id"])
            if not wait:
                return
            state = wait_until_done(client, accepted["id"])
    except httpx.HTTPError as error:
        raise fail(f"cannot talk to {server}: {type(error).__name__}: {error}") from None
    if state["status"] != "scored":
        reason = state.get("error") or "no reason given"
        raise fail(f"submission {state['id']} {state['status']}: {reason}")
    console.print(results_table(state))


def validate(
    file: Annotated[Path, typer.Argument(help="submission file to check")],
    split: Annotated[Path, typer.Option(help="split directory (holds scenes/)")],
) -> None:
    """Check a submission against a split locally, with the server's own checks; nothing is sent."""
    from scorer.scene import SceneFormatError, scene_paths
    from scorer.two_stage.split import MAPPING_FILE, TwoStageSplitError, load_two_stage_split
    from server.numbers import counted
    from server.services.errors import Invalid
    from server.services.validation import validate_upload

    if not file.is_file():
        raise fail(f"{file}: no such file")
    try:
        stages = load_two_stage_split(split) if (split / MAPPING_FILE).is_file() else None
        tokens = [*stages.stage_one_tokens, *stages.stage_two_tokens] if stages else list(scene_paths(split))
    except (SceneFormatError, TwoStageSplitError) as error:
        raise fail(str(error)) from None
    try:
        upload = validate_upload(file.read_bytes(), file.name, tokens, stages=stages)
    except Invalid as error:
        raise fail("\n".join([error.message, *problem_lines(error.problems)])) from None
    console.print(
        f"[green]valid[/green]: {counted(upload.seed_count, 'seed')} x {counted(upload.token_count, 'token')} of {split}, "
        f"sha256 {upload.sha256[:12]}…; the server would accept it"
    )


def register(app: typer.Typer) -> None:
    """Add `submit` and `validate` to `app`."""
    app.command()(submit)
    app.command()(validate)
