"""Hostile uploads and what they cost the API, watched from outside its process.

Shared by the hostile-upload tests and `benchmarks/hostile_uploads.py`: decompression bombs (files of a few MB
that inflate to hundreds of MiB or gigabytes, built in seconds), a process's memory read from /proc, and raw
HTTP requests whose body is sent only when the caller decides.

Each bomb comes with the words the API's
refusal must hold: a bomb of zeros is named by its first inflated bytes, one shaped like a submission (JSON that
opens an object and goes on blank, a pickle header followed by nothing a pickle holds) is stopped at the split's
limit, a bomb compressed again is named as such, and a zip archive is not read at all.
"""

from __future__ import annotations

import gzip
import io
import lzma
import re
import socket
import struct
import zipfile
import zlib
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import NamedTuple

GZIP_BOMB_BYTES = 2 << 30  # what a gzip bomb inflates to: about 2 MB of gzip, built in about a second
XZ_BOMB_BYTES = 256 << 20  # xz has no shortcut: its compressor takes about 10 ms per MiB even of zeros
BLOCK_BYTES = 1 << 20
JSON_START = b'{"predictions": '
PICKLE_START = b"\x80\x04"


def gzip_bomb(head: bytes = b"", fill: int = 0, size: int = GZIP_BOMB_BYTES) -> bytes:
    """Return a gzip file of `head` then bytes `fill` up to `size` bytes. A deflate block of 1 MiB ended by a full
    flush compresses to the same bytes each time (the compressor starts afresh), so it is compressed once and
    repeated; the trailer's CRC is that of the whole content, so every gzip reader takes the file as sound."""
    block = bytes([fill]) * BLOCK_BYTES
    first = head + block[len(head) :]
    deflate = zlib.compressobj(9, zlib.DEFLATED, -15)
    first_deflated = deflate.compress(first) + deflate.flush(zlib.Z_FULL_FLUSH)
    repeated = deflate.compress(block) + deflate.flush(zlib.Z_FULL_FLUSH)
    count = size // BLOCK_BYTES
    crc = zlib.crc32(first)
    for _ in range(count - 1):
        crc = zlib.crc32(block, crc)
    header = b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\xff"  # deflate, no name, no time, unknown OS
    trailer = struct.pack("<II", crc, (count * BLOCK_BYTES) & 0xFFFFFFFF)
    return header + first_deflated + repeated * (count - 1) + deflate.flush() + trailer


def xz_bomb(head: bytes = b"", fill: int = 0, size: int = XZ_BOMB_BYTES) -> bytes:
    """Return an xz file of `head` then bytes `fill` up to `size` bytes."""
    block = bytes([fill]) * BLOCK_BYTES
    compressor = lzma.LZMACompressor(preset=0)
    parts = [compressor.compress(head + block[len(head) :])]
    parts += [compressor.compress(block) for _ in range(size // BLOCK_BYTES - 1)]
    return b"".join([*parts, compressor.flush()])


def zip_bomb() -> bytes:
    """Return a zip archive of one member that inflates to 256 MiB of zeros."""
    buffer = io.BytesIO()
    with (
        zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive,
        archive.open("submission.json", "w", force_zip64=True) as member,
    ):
        for _ in range(ZIP_BOMB_BYTES // BLOCK_BYTES):
            member.write(bytes(BLOCK_BYTES))
    return buffer.getvalue()


class Bomb(NamedTuple):
    make: Callable[[], bytes]
    inflates_to: int  # bytes (the innermost layer's, for a bomb compressed again)
    words: str  # what the API's 422 says


ZIP_BOMB_BYTES = 256 * BLOCK_BYTES
BOMBS: dict[str, Bomb] = {
    "gzip bomb of zeros": Bomb(
        cache(gzip_bomb), GZIP_BOMB_BYTES, "gzip holding data starting with the bytes 00 00"
    ),
    "xz bomb of zeros": Bomb(cache(xz_bomb), XZ_BOMB_BYTES, "xz holding data starting with the bytes 00 00"),
    "gzip bomb shaped like JSON": Bomb(
        cache(lambda: gzip_bomb(JSON_START, ord(" "))), GZIP_BOMB_BYTES, "(gzip) decompresses to more than"
    ),
    "xz bomb shaped like a pickle": Bomb(
        cache(lambda: xz_bomb(PICKLE_START)), XZ_BOMB_BYTES, "(xz) decompresses to more than"
    ),
    "gzip bomb in gzip": Bomb(
        cache(lambda: gzip.compress(gzip_bomb(), 1)), GZIP_BOMB_BYTES, "gzip holding gzip"
    ),
    "zip bomb": Bomb(cache(zip_bomb), ZIP_BOMB_BYTES, "is a zip archive, not a submission"),
}


def memory_bytes(pid: int, field: str = "VmRSS") -> int:
    """Return a memory figure of process `pid` from /proc: VmRSS (resident now) or VmHWM (its peak)."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith(f"{field}:"))) * 1024


def reset_peak_memory(pid: int) -> None:
    """Set the peak (VmHWM) of process `pid` back to what it holds now."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def connect(url: str) -> socket.socket:
    """Open a TCP connection to the server at `url` (http://host:port)."""
    host, port = url.removeprefix("http://").split(":")
    return socket.create_connection((host, int(port)), timeout=10)


def upload_head(url: str, route: str, authorization: str | None, framing: str) -> bytes:
    """Return the head of an upload request (multipart, boundary x) with `framing` (Content-Length or chunked)."""
    host = url.removeprefix("http://").split(":")[0]
    authorization_line = f"Authorization: {authorization}\r\n" if authorization else ""
    return (
        f"POST {route} HTTP/1.1\r\nHost: {host}\r\n{authorization_line}"
        f"Content-Type: multipart/form-data; boundary=x\r\n{framing}\r\n\r\n"
    ).encode()


def read_response(connection: socket.socket) -> bytes:
    """Read one HTTP response: its head, then as many body bytes as its Content-Length says."""
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += connection.recv(1 << 16)
    head, _, body = answer.partition(b"\r\n\r\n")
    length = int(re.search(rb"content-length: (\d+)", head, re.IGNORECASE).group(1))  # type: ignore[union-attr]
    while len(body) < length:
        body += connection.recv(1 << 16)
    return head + b"\r\n\r\n" + body
