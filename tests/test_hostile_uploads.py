"""Hostile uploads over HTTP: each is answered 4xx with a message that says what is wrong, nothing is stored or
queued, and nothing the file names is executed: pickles that call os.system, eval or subprocess or import other
modules, unknown classes, object arrays, gzip, xz, zip and nested bombs (refused as they inflate, the API's
memory flat), files that are no submission at all (named by what they are), NaN and Inf, wrong shapes and
dtypes, missing, extra and duplicate tokens, invalid UTF-8, deeply nested or huge JSON; hostile file names are
only labels. An upload whose token is refused is answered before any of its body is sent."""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import pickle
import subprocess
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from select import select as wait_readable

import httpx
import numpy as np
import pytest
from hostile import (
    BOMBS,
    connect,
    memory_bytes,
    read_response,
    reset_peak_memory,
    upload_head,
)
from server_testing import REFERENCE_SUBMISSIONS, World
from sqlalchemy import func, select
from worker_testing import Service, SplitFixture, running_service

from server.db import transaction
from server.models import Approval, AuditEntry, Scope, Submission
from server.services.teams import create_team
from server.services.tokens import create_token

HUMAN = (REFERENCE_SUBMISSIONS / "human.json").read_bytes()
MARKER = Path(os.environ.get("TMPDIR", "/tmp")) / f"navsim-lb-hostile-{os.getpid()}"


class _Calls:
    """Pickles as `__reduce__` makes them: unpickling calls `function(*arguments)`."""

    def __init__(self, function: Callable[..., object], *arguments: object) -> None:
        self.function, self.arguments = function, arguments

    def __reduce__(self) -> tuple[object, tuple[object, ...]]:
        return self.function, self.arguments


def _in_submission(payload: object) -> bytes:
    return pickle.dumps({"team_name": "t", "predictions": [{"a1": payload}]}, protocol=4)


def _document(edit: Callable[[dict], None]) -> bytes:
    document = json.loads(HUMAN)
    edit(document)
    return json.dumps(document, allow_nan=True).encode()


def _first_token(document: dict) -> str:
    return min(document["predictions"])


def _nested(depth: int) -> bytes:
    return b'{"format": ' + b"[" * depth + b"]" * depth + b"}"


def _duplicate_token() -> bytes:
    text = HUMAN.decode()
    token = _first_token(json.loads(HUMAN))
    value = json.dumps(json.loads(HUMAN)["predictions"][token])
    return text.replace(f'"{token}":', f'"{token}": {value}, "{token}":', 1).encode()


# (case, bytes, words the message must contain)
HOSTILE: list[tuple[str, Callable[[], bytes], str]] = [
    ("pickle calls os.system", lambda: _in_submission(_Calls(os.system, f"touch {MARKER}")), "never holds"),
    ("pickle calls eval", lambda: _in_submission(_Calls(eval, f"open({str(MARKER)!r}, 'w')")), "never holds"),
    (
        "pickle calls subprocess",
        lambda: _in_submission(_Calls(subprocess.call, ["touch", str(MARKER)])),
        "never holds",
    ),
    (
        "pickle imports a module",
        lambda: _in_submission(_Calls(importlib.import_module, "antigravity")),
        "never holds",
    ),
    ("pickle holds an unknown class", lambda: _in_submission(OrderedDict(a=1)), "never holds"),
    (
        "pickle holds an object array",
        lambda: _in_submission(np.array([[0.0] * 3] * 8, dtype=object)),
        "dtype 'O8' is not allowed",
    ),
    *((name, bomb.make, bomb.words) for name, bomb in BOMBS.items()),
    ("a .pkl of no pickle", lambda: b"token,x,y,heading\n", "is text starting 'token,x,y,heading"),
    (
        "NaN pose",
        lambda: _document(lambda d: d["predictions"][_first_token(d)][0].__setitem__(0, float("nan"))),
        "finite",
    ),
    (
        "Inf pose",
        lambda: _document(lambda d: d["predictions"][_first_token(d)][1].__setitem__(1, float("inf"))),
        "finite",
    ),
    (
        "wrong shape",
        lambda: _document(lambda d: d["predictions"].__setitem__(_first_token(d), [[0.0, 0.0]] * 8)),
        "shape",
    ),
    (
        "text for a number",
        lambda: _document(lambda d: d["predictions"][_first_token(d)][0].__setitem__(0, "1.0")),
        "text",
    ),
    ("missing token", lambda: _document(lambda d: d["predictions"].pop(_first_token(d))), "missing"),
    (
        "extra token",
        lambda: _document(lambda d: d["predictions"].__setitem__("f" * 16, [[0.0] * 3] * 8)),
        "not in the split",
    ),
    ("duplicate token", _duplicate_token, "more than once"),
    ("invalid UTF-8", lambda: HUMAN.replace(b'"format"', b'"form\xff\xfet"', 1), "not valid JSON"),
    ("deeply nested JSON", lambda: _nested(100_000), "nested too deeply"),
    # Past what a submission of the split can take, it is not parsed.
    ("huge JSON of no submission", lambda: b"[" + b"0," * 20_000_000 + b"0]", "is more than"),
]


def _state(world: World) -> tuple[int, int, list[Path]]:
    """Everything stored: submissions, audit events and the stored files."""
    with world.session() as session:
        submissions = session.scalar(select(func.count()).select_from(Submission)) or 0
        events = session.scalar(select(func.count()).select_from(AuditEntry)) or 0
    return submissions, events, sorted(p for p in Path(world.settings.storage_dir).rglob("*") if p.is_file())


@pytest.mark.parametrize(("case", "make", "words"), HOSTILE, ids=[case for case, _, _ in HOSTILE])
def test_a_hostile_upload_is_refused_with_its_reason_and_changes_nothing(
    world: World, case: str, make: Callable[[], bytes], words: str
) -> None:
    before = _state(world)
    for route in ("/api/v1/submissions", "/api/v1/submissions:validate"):
        response = world.client.post(
            route,
            headers=world.team_headers(),
            files={"file": ("entry.pkl", make())},
            data={"phase": world.phase},
        )
        assert 400 <= response.status_code < 500, (case, response.status_code, response.text[:300])
        assert words in response.text, (case, response.text[:500])
        assert "Traceback" not in response.text and str(world.settings.data_dir) not in response.text
    assert _state(world) == before and world.queued == []
    assert not MARKER.exists()


def test_hostile_file_names_and_metadata_are_labels_only(world: World) -> None:
    traversal = "../../../../tmp/navsim-lb-traversal.json"
    response = world.client.post(
        "/api/v1/submissions",
        headers=world.team_headers(),
        files={"file": (traversal, HUMAN)},
        data={"phase": world.phase, "method": "../../etc/passwd", "authors": "<script>alert(1)</script>"},
    )
    assert response.status_code == 202, response.text
    stored = sorted(p.name for p in Path(world.settings.storage_dir).rglob("*") if p.is_file())
    sha256 = hashlib.sha256(HUMAN).hexdigest()
    assert stored == [sha256, f"{sha256}.npz"]  # the file and its parsed trajectories, named by its content
    assert not Path("/tmp/navsim-lb-traversal.json").exists()
    detail = world.client.get(response.headers["Location"], headers=world.team_headers()).json()
    assert (detail["method"], detail["authors"]) == ("../../etc/passwd", "<script>alert(1)</script>")


UPLOAD_LIMIT = 32 << 20  # MAX_UPLOAD_BYTES of the service below
FLAT_BYTES = 100 << 20  # what hostile uploads may add to the API's peak memory


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory, synthetic_split: SplitFixture) -> Iterator[Service]:
    """A real API process (and its worker), whose memory and sockets the tests watch from outside."""
    root = tmp_path_factory.mktemp("hostile-service")
    with running_service(root, synthetic_split, {"MAX_UPLOAD_BYTES": str(UPLOAD_LIMIT)}) as running:
        yield running


def _stream_until_answered(service: Service, limit: int, declared: int | None = None) -> tuple[int, bytes]:
    """Stream an upload that never ends until the API answers; return the bytes sent and the answer.

    With `declared`, the request says it holds that many bytes (Content-Length); otherwise it is chunked.
    """
    framing = f"Content-Length: {declared}" if declared else "Transfer-Encoding: chunked"
    head = upload_head(service.url, "/api/v1/submissions", f"Bearer {service.team_token}", framing)
    preamble = b'--x\r\nContent-Disposition: form-data; name="file"; filename="big.json"\r\n\r\n'
    # Blanks, which may start a JSON file: only the size refuses it (the API reads a file as it streams, and
    # would refuse another kind of content at its first bytes).
    block = b" " * (1 << 20)
    if declared:
        first, frame = preamble, block
    else:
        first, frame = (
            b"%x\r\n" % len(preamble) + preamble + b"\r\n",
            b"%x\r\n" % len(block) + block + b"\r\n",
        )
    sent = 0
    with connect(service.url) as connection:
        connection.sendall(head + first)
        while sent < 8 * limit and not wait_readable([connection], [], [], 0)[0]:
            try:
                connection.sendall(frame)
            except (BrokenPipeError, ConnectionResetError, TimeoutError):
                break
            sent += len(block)
        return sent, read_response(connection)


def test_an_oversized_upload_is_refused_while_it_streams(service: Service) -> None:
    before = memory_bytes(service.api.pid)
    # Declared too large: refused before the body is read. Not declared (chunked): read as it streams and
    # refused at the first limit it passes, not at its end: the split's (what a file of its tokens can take,
    # below the upload limit here).
    for declared, status, words in (
        (8 * UPLOAD_LIMIT, b"413", f"limit of {UPLOAD_LIMIT} bytes"),
        (None, b"422", "big.json is more than"),
    ):
        sent, answer = _stream_until_answered(service, UPLOAD_LIMIT, declared)
        assert answer.startswith(b"HTTP/1.1 " + status), answer[:200]
        assert words.encode() in answer, answer
        assert sent < 2 * UPLOAD_LIMIT, (
            f"the API read {sent / 2**20:.0f} MiB of {UPLOAD_LIMIT / 2**20:.0f} MiB"
        )
    grown = memory_bytes(service.api.pid) - before
    assert grown < UPLOAD_LIMIT // 2, f"the API grew by {grown / 2**20:.0f} MiB"
    assert service.rows(1) == 0 and not any(service.settings.storage_dir.iterdir())


def test_bombs_are_refused_as_they_inflate_and_the_api_memory_stays_flat(service: Service) -> None:
    bombs = {name: bomb.make() for name, bomb in BOMBS.items()}

    def upload(name: str) -> httpx.Response:
        return client.post(
            "/api/v1/submissions", files={"file": ("entry.pkl", bombs[name])}, data={"phase": "test"}
        )

    with service.client() as client:
        for name in bombs:  # once first: the API's first imports and allocations are not what a bomb costs
            upload(name)
        reset_peak_memory(service.api.pid)
        before = memory_bytes(service.api.pid)
        with ThreadPoolExecutor(4) as pool:  # several at once, as a flood would come
            answers = dict(zip([*bombs, *bombs], pool.map(upload, [*bombs, *bombs]), strict=True))
        grown = memory_bytes(service.api.pid, "VmHWM") - before
    inflated = 2 * sum(bomb.inflates_to for bomb in BOMBS.values())
    assert grown < FLAT_BYTES, f"bombs of {inflated / 2**30:.1f} GiB grew the API by {grown / 2**20:.0f} MiB"
    for name, response in answers.items():
        assert response.status_code == 422, (name, response.text[:300])
        assert BOMBS[name].words in response.text, (name, response.text[:500])
    assert service.rows(1) == 0 and not any(service.settings.storage_dir.iterdir())


def _pending_team_token(service: Service) -> str:
    with transaction(service.factory) as session:
        team = create_team(session, "not yet approved", ["a member"], "a lab", Approval.pending)
        return create_token(session, Scope.team, team, "test")[1]


@pytest.mark.parametrize(
    ("route", "authorization", "status", "words"),
    [
        ("/api/v1/submissions", None, 401, "missing API token"),
        ("/api/v1/submissions", "Bearer nlb_not-a-token", 401, "unknown API token"),
        ("/api/v1/submissions:validate", "Bearer nlb_not-a-token", 401, "unknown API token"),
        ("/api/v1/submissions", "Basic YWxpY2U6c2VjcmV0", 401, "malformed Authorization header"),
        ("/api/v1/submissions", "pending team", 403, "an admin must approve it first"),
    ],
)
def test_an_upload_is_refused_for_its_token_before_any_of_its_body_is_sent(
    service: Service, route: str, authorization: str | None, status: int, words: str
) -> None:
    if authorization == "pending team":
        authorization = f"Bearer {_pending_team_token(service)}"
    declared = UPLOAD_LIMIT  # within the limit: only the token can have it refused
    head = upload_head(service.url, route, authorization, f"Content-Length: {declared}")
    with connect(service.url) as connection:
        connection.sendall(head)
        # Not one byte of the body is sent until the answer is there (a deadline against hanging: an API that
        # waits for the body never answers).
        answered = wait_readable([connection], [], [], 20)[0]
        assert answered, "the API waited for the body of an upload whose token it refuses"
        answer = read_response(connection)
    assert answer.startswith(f"HTTP/1.1 {status}".encode()), answer[:300]
    assert words.encode() in answer and b"connection: close" in answer.lower(), answer
