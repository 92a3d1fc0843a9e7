"""An upload flows once: read as it streams, hashed, written to the store a part at a time and parsed on the
way, so that the API holds about one part of it (and the parsed poses), never the file; an upload refused
for any reason leaves neither a row nor an object, on a local directory and in an S3 store alike."""

from __future__ import annotations

import hashlib
import json
import time
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from object_stores import fresh_s3_store
from server_testing import REFERENCE_SUBMISSIONS, World
from test_object_store import _leftovers

from server.models import Submission
from server.object_store import PART_BYTES, LocalStore, ObjectStore, S3Store
from server.services.validation import Received, validate_stream
from server.settings import Settings
from server.storage import stored_name
from server.upload_form import UploadForm

HUMAN = (REFERENCE_SUBMISSIONS / "human.json").read_bytes()
TOKENS = [f"{index:032x}" for index in range(12_000)]
SEEDS = 3


def _pieces(tokens: list[str]) -> Iterator[bytes]:
    """Yield a navtest-size submission (indented: about 90 MB) a token at a time, never whole."""
    rng = np.random.default_rng(0)
    yield b'{"format": "navsim-lb/submission", "version": 1, "predictions": ['
    for seed in range(SEEDS):
        yield b"{" if seed == 0 else b", {"
        for index, token in enumerate(tokens):
            poses = json.dumps(rng.normal(size=(8, 3)).tolist(), indent=8)
            yield (b", " if index else b"") + json.dumps(token).encode() + b": " + poses.encode()
        yield b"}"
    yield b"]}"


class _Generated:
    """A file read from a generator of pieces (what an HTTP body gives), never held whole."""

    def __init__(self, pieces: Iterator[bytes]) -> None:
        self.pieces, self.pending = pieces, b""

    def read(self, size: int = -1) -> bytes:
        while len(self.pending) < size and (piece := next(self.pieces, b"")):
            self.pending += piece
        data, self.pending = self.pending[:size], self.pending[size:]
        return data


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> ObjectStore:
    return LocalStore(tmp_path / "store") if request.param == "local" else fresh_s3_store()


def test_a_large_upload_costs_about_one_part_of_memory_beyond_its_poses(store: ObjectStore) -> None:
    tracemalloc.start()
    try:
        before, cpu = tracemalloc.get_traced_memory()[0], time.process_time()
        with store.staging() as staged:
            received = Received(_Generated(_pieces(TOKENS)), staged.write)
            upload = validate_stream(received, "big.json", TOKENS, staged=staged)
            staged.commit(stored_name(upload.sha256))
        cpu = time.process_time() - cpu
        held, peak = (
            tracemalloc.get_traced_memory()
        )  # `upload` holds the parsed poses: tokens x seeds x 8 x 3
    finally:
        tracemalloc.stop()
    beyond = (peak - held) / 2**20
    print(
        f"{store.url.split(':')[0]}: a {upload.size_bytes / 2**20:.0f} MiB upload ({cpu:.1f} CPU-s with the"
        f" file's making): peak {(peak - before) / 2**20:.0f} MiB, of which the parsed poses"
        f" {(held - before) / 2**20:.0f} MiB and {beyond:.1f} MiB beyond them"
    )
    assert upload.size_bytes > 4 * PART_BYTES
    assert beyond < PART_BYTES / 2**20 + 8, f"{beyond:.0f} MiB held beyond the parsed poses"
    stored = store.get(stored_name(upload.sha256))
    assert hashlib.sha256(stored).hexdigest() == upload.sha256 and len(stored) == upload.size_bytes
    # The same poses, bit for bit, as the whole file read at once by json.loads.
    whole = json.loads(stored)["predictions"]
    for seed, poses in zip(upload.trajectories, whole, strict=True):
        assert all(np.array_equal(seed[token], np.array(poses[token])) for token in TOKENS[::97])
    assert not [name for name in _leftovers(store) if isinstance(store, S3Store) or name.startswith(".")]


@pytest.fixture(params=["local", "s3"])
def server_settings(request: pytest.FixtureRequest, server_settings: Settings) -> Settings:
    if request.param == "local":
        return server_settings
    return server_settings.model_copy(update={"storage_url": fresh_s3_store().url})


def _post(world: World, data: bytes, **fields: str) -> tuple[int, str]:
    response = world.client.post(
        "/api/v1/submissions",
        headers=world.team_headers(),
        files={"file": ("human.json", data)},
        data=fields,
    )
    return response.status_code, response.text


def _nothing_left(world: World) -> bool:
    store = world.settings.submission_store
    with world.factory() as session:
        rows = session.query(Submission).count()
    return rows == 0 and store.keys("") == [] and _leftovers(store) == []


def test_a_refused_upload_leaves_no_row_and_no_object(world: World) -> None:
    # Refused at its end, after it was written to the store (as much as the test split's limit lets a file
    # hold: parts sent and then abandoned are tested with the stores), and as a duplicate of itself.
    padded = HUMAN[:-1] + b" " * (3 << 20) + b"}"
    for data in (padded[:-1], padded.replace(b'"format"', b'"formats"', 1)):
        status, text = _post(world, data)
        assert status == 422 and _nothing_left(world), text
    status, text = _post(world, padded)
    assert status == 202, text
    name = stored_name(hashlib.sha256(padded).hexdigest())
    assert world.settings.submission_store.get(name) == padded
    status, text = _post(world, padded)
    assert status == 409, text
    assert world.settings.submission_store.keys("") == [name, f"{name}.npz"]


def test_fields_after_the_file_are_read_once_the_file_is(world: World) -> None:
    body = (
        b"--b\r\n".join(
            [
                b"",
                b'Content-Disposition: form-data; name="file"; filename="human.json"\r\n\r\n'
                + HUMAN
                + b"\r\n",
                b'Content-Disposition: form-data; name="method"\r\n\r\nLate Method\r\n',
            ]
        )
        + b"--b--\r\n"
    )
    headers = {**world.team_headers(), "Content-Type": "multipart/form-data; boundary=b"}
    accepted = world.client.post("/api/v1/submissions", headers=headers, content=body)
    assert accepted.status_code == 202, accepted.text
    with world.factory() as session:
        assert session.query(Submission.method).scalar() == "Late Method"
    # Read as it arrives, a chunk at a time (the test client sends a body whole): what comes after the file is
    # known only once the file is read, and a phase there is refused unless the file was read for it.
    form = UploadForm(iter([body[:60], body[60:-40], body[-40:]]), headers["Content-Type"])
    form.start_file()
    assert form.filename == "human.json" and form.fields == {}
    assert b"".join(iter(lambda: form.read(1000), b"")) == HUMAN
    assert form.fields == {"method": "Late Method"} and form.after_file == {"method"}
    no_file = world.client.post("/api/v1/submissions", headers=headers, content=b"--b--\r\n")
    assert no_file.status_code == 422 and "no `file` field" in no_file.text
