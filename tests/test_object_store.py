"""The object store's two backends behave alike: streamed (multipart) writes read back whole, a conditional
write lets exactly one writer in, keys list by prefix, a missing object is a FileNotFoundError; and an S3
endpoint that does not answer is StoreUnavailable, the error callers retry (never a crash or a wrong read)."""

from __future__ import annotations

import io
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from object_stores import fresh_s3_store
from worker_testing import free_port

from server.object_store import (
    PART_BYTES,
    LocalStore,
    MissingObject,
    ObjectStore,
    S3Store,
    StoreUnavailable,
    _client_of,
    child,
    connect,
    open_store,
)


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> ObjectStore:
    return LocalStore(tmp_path / "store") if request.param == "local" else fresh_s3_store()


class _CountingReader(io.BytesIO):
    """A stream that remembers the largest read asked of it."""

    largest = 0

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        self.largest = max(self.largest, len(data))
        return data


def test_a_streamed_write_of_several_parts_reads_back_whole(store: ObjectStore, tmp_path: Path) -> None:
    data = os.urandom(2 * PART_BYTES + 12345)  # three parts of a multipart upload
    source = _CountingReader(data)
    store.put("ab/file", source)
    assert store.get("ab/file") == data
    assert source.largest <= PART_BYTES  # never read whole into memory
    store.download("ab/file", tmp_path / "copy")
    assert (tmp_path / "copy").read_bytes() == data


def test_one_conditional_writer_wins_and_the_object_is_whole(store: ObjectStore) -> None:
    with ThreadPoolExecutor(4) as pool:
        won = list(pool.map(lambda n: store.put_if_absent("cache/x", bytes([n]) * 1000), range(8)))
    assert sum(won) == 1
    assert store.get("cache/x") == bytes([won.index(True)]) * 1000


def test_keys_list_by_prefix_and_a_missing_object_is_a_missing_file(store: ObjectStore) -> None:
    for key in ("scenes/b.json", "scenes/a.json.gz", "other/c"):
        store.put_bytes(key, key.encode())
    assert store.keys("scenes/") == ["scenes/a.json.gz", "scenes/b.json"]
    assert child(store, "scenes").get("b.json") == b"scenes/b.json"
    with pytest.raises(MissingObject):
        store.get("scenes/none.json")
    with pytest.raises(FileNotFoundError):
        store.get("scenes/none.json")


def test_store_urls_name_a_directory_or_a_bucket_and_prefix(tmp_path: Path) -> None:
    assert open_store(tmp_path) == LocalStore(tmp_path)
    assert open_store("s3://bucket/a/b/") == S3Store("bucket", "a/b")
    assert open_store("s3://bucket").url == "s3://bucket"
    with pytest.raises(ValueError, match="s3://bucket/prefix"):
        open_store("s3:///prefix")


def test_an_s3_endpoint_that_does_not_answer_is_unavailable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{free_port()}")
    store = S3Store("bucket", "prefix")
    for call in (lambda: store.get("x"), lambda: store.put_bytes("x", b"1"), lambda: store.keys("")):
        with pytest.raises(StoreUnavailable, match="cannot be reached"):
            call()
    with pytest.raises(StoreUnavailable):
        store.put("big", io.BytesIO(b"x" * 10))


def test_connecting_makes_the_s3_client_at_once_and_reaches_nothing(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    endpoint = f"http://127.0.0.1:{free_port()}"  # nothing listens: connecting must not call the store
    monkeypatch.setenv("AWS_ENDPOINT_URL", endpoint)
    _client_of.cache_clear()
    connect(LocalStore(tmp_path / "store"))
    assert _client_of.cache_info().currsize == 0
    connect(S3Store("bucket", "prefix"))
    made = _client_of(endpoint)
    assert _client_of.cache_info().hits == 1  # the call above found the client connect made
    assert made.meta.endpoint_url == endpoint


def _leftovers(store: ObjectStore) -> list[str]:
    """What a store holds besides its objects: hidden temporary files, or unfinished multipart uploads."""
    if isinstance(store, LocalStore):
        return sorted(path.name for path in store.root.rglob("*")) if store.root.exists() else []
    import boto3

    assert isinstance(store, S3Store)
    listed = boto3.client("s3").list_multipart_uploads(Bucket=store.bucket, Prefix=f"{store.prefix}/")
    return [upload["Key"] for upload in listed.get("Uploads", [])]


def test_a_staged_object_appears_under_its_key_only_when_committed(store: ObjectStore) -> None:
    data = os.urandom(2 * PART_BYTES + 12345)  # three parts of a multipart upload
    with store.staging() as staged:
        for start in range(0, len(data), 1 << 20):
            staged.write(data[start : start + (1 << 20)])
        assert store.keys("") == []
        staged.commit("ab/file")
    assert store.get("ab/file") == data and store.keys("") == ["ab/file"]
    with store.staging() as staged:  # one part: sent whole at the end
        staged.write(b"small")
        staged.commit("ab/small")
    assert store.get("ab/small") == b"small" and store.keys("") == ["ab/file", "ab/small"]
    assert _leftovers(store) == ([] if isinstance(store, S3Store) else ["ab", "file", "small"])


def test_a_staged_object_left_uncommitted_leaves_nothing(store: ObjectStore) -> None:
    with pytest.raises(RuntimeError), store.staging() as staged:
        staged.write(os.urandom(PART_BYTES + 1))  # one part sent
        raise RuntimeError("the upload was refused")
    with store.staging() as staged:
        staged.write(b"never named")
    assert store.keys("") == [] and _leftovers(store) == []
