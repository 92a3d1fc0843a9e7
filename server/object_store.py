"""Where uploads, split scenes and published metric caches live: a local directory, or an S3-compatible store.

One narrow interface (`ObjectStore`: put a stream or bytes, put only if absent, get, download, list) with two
backends, chosen by one URL (`open_store`): a directory (the embedded default: `make demo` and the tests need no
object store), or `s3://bucket/prefix` for AWS S3, MinIO, Ceph RGW and other stores of the S3 API, with the
endpoint, keys and region from the standard AWS_* variables (boto3 reads them: AWS_ENDPOINT_URL,
AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_DEFAULT_REGION). That lets a worker run on any machine with a
database URL, a broker URL and store credentials, sharing no filesystem with the API.

A write is whole or absent on both: a file is renamed into place, an S3 object appears when its (multipart)
upload completes. An unreachable store raises `StoreUnavailable` (the API answers 503, a chunk retries); a
missing object raises `MissingObject`, a FileNotFoundError as a missing file would.
"""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import IO, Any, Protocol
from urllib.parse import urlsplit

from scorer.files import create_temporary_beside, write_atomically

log = logging.getLogger(__name__)
S3_SCHEME = "s3"
# Where a store's uploads are written until they are named (by their sha256, known at their end).
INCOMING_PREFIX = ".incoming"
# An upload goes to S3 in parts of this size: the most of it held in memory at once (S3's least part is 5 MiB).
PART_BYTES = 8 * 1024 * 1024
# Objects read at once by get_many (the S3 client is thread-safe; its pool holds as many connections).
FETCH_THREADS = 10
# A store that does not answer within these fails the call (retried by its caller), not the process.
CONNECT_TIMEOUT_S, READ_TIMEOUT_S, CALL_ATTEMPTS = 5.0, 30.0, 3


class StoreUnavailable(Exception):
    """The store could not be reached or refused the call: the same call may succeed later."""


class MissingObject(FileNotFoundError):
    """No object under the key."""


class ObjectStore(Protocol):
    """Objects by key ('a/b/c'): whole or absent, never a part. Equal stores compare and hash equal."""

    @property
    def url(self) -> str:
        """Where the objects are: a directory, or s3://bucket/prefix."""

    def __hash__(self) -> int:
        """Stores are keys of caches (a process's parsed files)."""

    def put(self, key: str, source: IO[bytes]) -> None:
        """Store what `source` reads, streamed (never whole in memory), under `key`."""

    def put_bytes(self, key: str, data: bytes) -> None:
        """Store `data` under `key`."""

    def put_if_absent(self, key: str, data: bytes) -> bool:
        """Store `data` under `key` unless an object is there already; return whether this call stored it."""

    def get(self, key: str) -> bytes:
        """Return the object's bytes (MissingObject when there is none)."""

    def download(self, key: str, path: Path) -> None:
        """Write the object to the local file `path` (whole, through a rename)."""

    def keys(self, prefix: str) -> list[str]:
        """Return the keys under `prefix`, sorted."""

    def staging(self) -> AbstractContextManager[Staged]:
        """Return a context in which an object is written as it arrives and named only at the end (an upload,
        by its sha256): whatever leaves it uncommitted, an error included, removes what was written."""


class Staged(Protocol):
    """An object being written, under no key until `commit`."""

    def write(self, data: bytes) -> None:
        """Append `data` (at most one part is held in memory)."""

    def commit(self, key: str) -> None:
        """Store what was written under `key` (whole, or not at all)."""


@dataclass(frozen=True)
class LocalStore:
    """Objects as files under a directory."""

    root: Path

    @property
    def url(self) -> str:
        return str(self.root)

    def _path(self, key: str) -> Path:
        return self.root / key

    def put(self, key: str, source: IO[bytes]) -> None:
        with _temporary_beside(self._path(key)) as (handle, temporary):
            shutil.copyfileobj(source, handle, PART_BYTES)
            handle.flush()
            os.fsync(handle.fileno())  # uploads cannot be made again
            os.replace(temporary, self._path(key))

    def put_bytes(self, key: str, data: bytes) -> None:
        write_atomically(self._path(key), data)

    def put_if_absent(self, key: str, data: bytes) -> bool:
        path = self._path(key)
        with _temporary_beside(path) as (handle, temporary):
            handle.write(data)
            handle.close()
            try:
                os.link(temporary, path)  # fails when the name exists: the first writer wins
            except FileExistsError:
                return False
        return True

    def get(self, key: str) -> bytes:
        try:
            return self._path(key).read_bytes()
        except (FileNotFoundError, NotADirectoryError):
            raise MissingObject(f"{self.url}: no object {key}") from None

    def download(self, key: str, path: Path) -> None:
        write_atomically(Path(path), self.get(key), durable=False)

    @contextmanager
    def staging(self) -> Iterator[Staged]:
        with _temporary_beside(self.root / "incoming") as (handle, temporary):
            yield _LocalStaged(self, handle, temporary)

    def keys(self, prefix: str) -> list[str]:
        base = self._path(prefix)
        if not base.is_dir():
            return []
        return sorted(
            f"{prefix.rstrip('/')}/{path.relative_to(base).as_posix()}".lstrip("/")
            for path in base.rglob("*")
            if path.is_file() and not path.name.startswith(".")
        )


@dataclass(frozen=True)
class _LocalStaged:
    """An object written to a hidden temporary file in the store's directory, renamed into place."""

    store: LocalStore
    handle: IO[bytes]
    temporary: str

    def write(self, data: bytes) -> None:
        self.handle.write(data)

    def commit(self, key: str) -> None:
        self.handle.flush()
        os.fsync(self.handle.fileno())  # uploads cannot be made again
        path = self.store._path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        os.replace(self.temporary, path)


@contextmanager
def _temporary_beside(path: Path) -> Iterator[tuple[IO[bytes], str]]:
    """Yield an open temporary file in `path`'s directory and its name; it is removed unless renamed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = create_temporary_beside(path)
    try:
        with os.fdopen(fd, "wb") as handle:
            yield handle, temporary
    finally:
        Path(temporary).unlink(missing_ok=True)


@dataclass(frozen=True)
class S3Store:
    """Objects in an S3 bucket under a key prefix (no slash at either end)."""

    bucket: str
    prefix: str

    @property
    def url(self) -> str:
        return f"{S3_SCHEME}://{self.bucket}/{self.prefix}".rstrip("/")

    def _key(self, key: str) -> str:
        return f"{self.prefix}/{key}" if self.prefix else key

    def put(self, key: str, source: IO[bytes]) -> None:
        from boto3.s3.transfer import TransferConfig

        # One part in memory at a time, sent by this thread: a multipart upload above PART_BYTES.
        config = TransferConfig(
            multipart_threshold=PART_BYTES, multipart_chunksize=PART_BYTES, use_threads=False
        )
        with _reaching(self):
            _client().upload_fileobj(source, self.bucket, self._key(key), Config=config)

    def put_bytes(self, key: str, data: bytes) -> None:
        with _reaching(self):
            _client().put_object(Bucket=self.bucket, Key=self._key(key), Body=data)

    def put_if_absent(self, key: str, data: bytes) -> bool:
        from botocore.exceptions import ClientError

        try:
            with _reaching(self, passing=("PreconditionFailed", "ConditionalRequestConflict")):
                _client().put_object(Bucket=self.bucket, Key=self._key(key), Body=data, IfNoneMatch="*")
        except ClientError as error:
            if _code(error) in ("PreconditionFailed", "ConditionalRequestConflict"):
                return False  # another writer stored it first (or is storing it now)
            raise
        return True

    def get(self, key: str) -> bytes:
        with _reaching(self):
            body: bytes = _client().get_object(Bucket=self.bucket, Key=self._key(key))["Body"].read()
        return body

    def download(self, key: str, path: Path) -> None:
        write_atomically(Path(path), self.get(key), durable=False)

    @contextmanager
    def staging(self) -> Iterator[Staged]:
        staged = _S3Staged(self, f"{INCOMING_PREFIX}/{uuid.uuid4().hex}")
        try:
            yield staged
        finally:
            staged.discard()

    def keys(self, prefix: str) -> list[str]:
        full = self._key(prefix)
        found: list[str] = []
        with _reaching(self):
            for page in _client().get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=full):
                found += [item["Key"] for item in page.get("Contents", [])]
        start = len(self.prefix) + 1 if self.prefix else 0
        return sorted(name[start:] for name in found)


class _S3Staged:
    """An object sent in PART_BYTES parts of a multipart upload under a temporary key, copied to its key at
    the end (S3 names an upload when it starts); a file of one part is sent whole to its key at the end."""

    def __init__(self, store: S3Store, temporary: str) -> None:
        self.store, self.temporary = store, store._key(temporary)
        self.buffer = bytearray()
        self.upload_id: str | None = None
        self.parts: list[dict[str, Any]] = []
        self.completed = False

    def _send_part(self) -> None:
        client, store = _client(), self.store
        with _reaching(store):
            if self.upload_id is None:
                started = client.create_multipart_upload(Bucket=store.bucket, Key=self.temporary)
                self.upload_id = started["UploadId"]
            number = len(self.parts) + 1
            sent = client.upload_part(
                Bucket=store.bucket,
                Key=self.temporary,
                UploadId=self.upload_id,
                PartNumber=number,
                Body=self.buffer,
            )
        self.parts.append({"PartNumber": number, "ETag": sent["ETag"]})
        self.buffer.clear()

    def write(self, data: bytes) -> None:
        self.buffer += data
        if len(self.buffer) >= PART_BYTES:
            self._send_part()

    def commit(self, key: str) -> None:
        from boto3.s3.transfer import TransferConfig

        store, client = self.store, _client()
        if self.upload_id is None:
            store.put_bytes(key, bytes(self.buffer))
            self.buffer.clear()
            return
        if self.buffer:
            self._send_part()
        with _reaching(store):
            client.complete_multipart_upload(
                Bucket=store.bucket,
                Key=self.temporary,
                UploadId=self.upload_id,
                MultipartUpload={"Parts": self.parts},
            )
            self.completed = True
            source = {"Bucket": store.bucket, "Key": self.temporary}
            # A managed copy: CopyObject, or a multipart copy above its limit, part by part on the store itself.
            client.copy(source, store.bucket, store._key(key), Config=TransferConfig(use_threads=False))

    def discard(self) -> None:
        """Remove the temporary upload or object (best effort: a store that is down keeps an incomplete
        upload, which S3 never shows as an object; a bucket's lifecycle rule removes it)."""
        from botocore.exceptions import BotoCoreError, ClientError

        store, client = self.store, _client()
        try:
            if self.completed:
                client.delete_object(Bucket=store.bucket, Key=self.temporary)
            elif self.upload_id is not None:
                client.abort_multipart_upload(
                    Bucket=store.bucket, Key=self.temporary, UploadId=self.upload_id
                )
        except (BotoCoreError, ClientError) as error:
            log.warning(
                "could not remove the temporary upload %s from %s: %s", self.temporary, store.url, error
            )


def get_many(store: ObjectStore, keys: Iterable[str]) -> dict[str, bytes | None]:
    """Return each key's bytes (None when there is no object), read FETCH_THREADS at a time: a chunk's few
    hundred scenes and caches cost one round trip each, which is latency, not bandwidth."""
    keys = list(dict.fromkeys(keys))

    def fetched(key: str) -> bytes | None:
        try:
            return store.get(key)
        except MissingObject:
            return None

    if len(keys) <= 1:
        return {key: fetched(key) for key in keys}
    with ThreadPoolExecutor(min(FETCH_THREADS, len(keys))) as pool:
        return dict(zip(keys, pool.map(fetched, keys), strict=True))


def _code(error: Any) -> str:
    return str(error.response.get("Error", {}).get("Code", ""))


@contextmanager
def _reaching(store: S3Store, passing: tuple[str, ...] = ()) -> Iterator[None]:
    """Translate the client's errors: a missing key to MissingObject, an unreachable or failing store to
    StoreUnavailable; an error code in `passing` is raised as it is."""
    from boto3.exceptions import S3UploadFailedError
    from botocore.exceptions import BotoCoreError, ClientError

    try:
        yield
    except ClientError as error:
        code = _code(error)
        if code in passing:
            raise
        if code in ("NoSuchKey", "404", "NotFound"):
            raise MissingObject(f"{store.url}: no object") from None
        raise StoreUnavailable(f"object store {store.url} refused the call ({code or error})") from None
    except (BotoCoreError, S3UploadFailedError) as error:
        raise StoreUnavailable(f"object store {store.url} cannot be reached ({error})") from None


def _client() -> Any:
    """Return this process's S3 client (thread-safe), configured from the AWS_* variables."""
    return _client_of(os.environ.get("AWS_ENDPOINT_URL"))


@lru_cache(maxsize=4)
def _client_of(endpoint: str | None) -> Any:
    """Return the S3 client of an endpoint (boto3 reads it, the keys and the region from the environment)."""
    import boto3
    from botocore.config import Config

    config = Config(
        connect_timeout=CONNECT_TIMEOUT_S,
        read_timeout=READ_TIMEOUT_S,
        retries={"mode": "standard", "max_attempts": CALL_ATTEMPTS},
        # A store of one's own (MinIO, moto, Ceph) is addressed by path; AWS by the bucket's host name.
        s3={"addressing_style": "path" if endpoint else "auto"},
    )
    return boto3.client("s3", config=config)


# A forked child (worker.isolated) makes its own: pooled connections shared with the parent would cross replies.
os.register_at_fork(after_in_child=_client_of.cache_clear)


def connect(store: ObjectStore) -> None:
    """Make this process's client of `store` now, at start (an S3 client's imports and service model cost about
    0.3 CPU-s, and twice that in wall time on a busy host): an upload or a chunk never waits on it."""
    if isinstance(store, S3Store):
        _client()


def is_store_url(location: str) -> bool:
    """Return whether `location` names an object store (s3://...) rather than a local directory."""
    return urlsplit(str(location)).scheme == S3_SCHEME


def open_store(location: str | Path) -> ObjectStore:
    """Return the store `location` names: `s3://bucket/prefix`, or a local directory."""
    if not is_store_url(str(location)):
        return LocalStore(Path(location))
    parts = urlsplit(str(location))
    if not parts.netloc:
        raise ValueError(f"{location!r}: an object store URL is s3://bucket/prefix")
    return S3Store(parts.netloc, parts.path.strip("/"))


def child(store: ObjectStore, prefix: str) -> ObjectStore:
    """Return the part of `store` under `prefix`, as a store of its own."""
    return open_store(f"{store.url.rstrip('/')}/{prefix}")
