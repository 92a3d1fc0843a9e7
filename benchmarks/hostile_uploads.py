"""What hostile uploads cost the API: its peak memory and time per decompression bomb, and how much of an
upload's body a refused token makes the client send.

One API process (uvicorn, embedded database) on a synthetic split of --tokens scenes (built on first use,
shared with benchmarks/service.py). The split's content limit (scorer.submission.ContentLimit: what a valid
submission of its tokens x 32 seeds x 8 poses can take) is printed beside a navtest-size split's. Then, each
measured from a peak (VmHWM) set back to the API's resident memory just before:
- the dry run of a valid entry of every token (1 seed), for scale;
- each bomb of tests/hostile.py alone (a first, untimed upload of each pays the API's first imports);
- --copies of every bomb, all at once (a client thread each);
- an upload with a wrong token that declares a body of 200 MiB: how many of its bytes were sent before the
  401 arrived (the client sends none until it has the answer or has waited 10 s).

Usage: .venv/bin/python benchmarks/hostile_uploads.py [--tokens 2000] [--copies 2]
"""

from __future__ import annotations

# isort: off
import scorer  # noqa: F401 - before numpy, so that numpy loads the official results' OpenBLAS kernels

# isort: on
import argparse
import os
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from pathlib import Path
from select import select as wait_readable

import httpx
from host import host_header
from service import answers, entry_file, free_port, set_up, synthesized_split, wait_until

from navsim_lb.processes import api_command, child_process
from scorer.scene import scene_paths
from scorer.submission import ContentLimit
from server.settings import Settings

# service.py put tests/ on the path: the bombs and the /proc readings are the tests' own.
from hostile import BOMBS, connect, memory_bytes, read_response, reset_peak_memory, upload_head  # isort: skip

NAVTEST_TOKENS = 12_146
NAVSIM_TOKEN = "0" * 16  # NAVSIM's tokens are 16 hexadecimal digits
DECLARED_BYTES = 200 << 20


def mib(size: float) -> str:
    return f"{size / 2**20:,.1f} MiB" if abs(size) >= 2**20 else f"{size / 2**10:,.0f} KiB"


def measured(pid: int, action: Callable[[], list[httpx.Response]]) -> tuple[list[httpx.Response], float, int]:
    """Run `action`; return its answers, its seconds and how far the API's peak memory rose above what it held
    before."""
    reset_peak_memory(pid)
    before = memory_bytes(pid)
    started = time.perf_counter()
    responses = action()
    return responses, time.perf_counter() - started, max(0, memory_bytes(pid, "VmHWM") - before)


def answered_before_the_body(url: str) -> tuple[bytes, int, float]:
    """Send the head of an upload with a wrong token and a declared body of DECLARED_BYTES, and none of the body
    until an answer comes (or 10 s pass, then all of it); return the answer, the body bytes sent and the ms."""
    route, authorization = "/api/v1/submissions", "Bearer nlb_not-a-token"
    with connect(url) as connection:
        started = time.perf_counter()
        connection.sendall(upload_head(url, route, authorization, f"Content-Length: {DECLARED_BYTES}"))
        sent = 0
        if not wait_readable([connection], [], [], 10)[0]:
            block = bytes(1 << 20)
            while sent < DECLARED_BYTES and not wait_readable([connection], [], [], 0)[0]:
                connection.sendall(block)
                sent += len(block)
        answer = read_response(connection)
        return answer, sent, (time.perf_counter() - started) * 1000


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--tokens", type=int, default=2000)
    parser.add_argument("--copies", type=int, default=2, help="copies of each bomb sent at once")
    args = parser.parse_args()
    print("\n".join(host_header()), flush=True)

    split = synthesized_split(args.tokens)
    limit = ContentLimit.for_tokens(scene_paths(split))
    navtest = ContentLimit.for_tokens([NAVSIM_TOKEN] * NAVTEST_TOKENS)
    print(
        f"content limit: {mib(limit.bytes)} for this split ({args.tokens} tokens), {mib(navtest.bytes)} for a "
        f"navtest-size split ({NAVTEST_TOKENS:,} tokens)"
    )
    bombs = {name: bomb.make() for name, bomb in BOMBS.items()}
    with tempfile.TemporaryDirectory(prefix="navsim-lb-hostile-") as tmp, ExitStack() as stack:
        root = Path(tmp)
        variables = {"DATA_DIR": str(root), "SPLITS": "{}"}
        token, _ = set_up(Settings(data_dir=root).database_url, split)
        port = free_port()
        api = stack.enter_context(
            child_process(api_command("127.0.0.1", port), {**os.environ, **variables}, root / "api.log")
        )
        url = f"http://127.0.0.1:{port}"
        client = stack.enter_context(
            httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=300)
        )
        wait_until(lambda: answers(client), timeout=60)

        def post(name: str, data: bytes, route: str = "/api/v1/submissions") -> httpx.Response:
            return client.post(route, files={"file": (name, data)}, data={"phase": "bench"})

        entry = entry_file(split, root / "entry.json").read_bytes()
        [response], seconds, grown = measured(
            api.pid, lambda: [post("entry.json", entry, "/api/v1/submissions:validate")]
        )
        assert response.status_code == 200, response.text
        print(
            f"API resident before: {mib(memory_bytes(api.pid))}; a valid entry of {args.tokens} tokens x 1 seed "
            f"({mib(len(entry))} of JSON), dry run: {seconds:.2f} s, peak +{mib(grown)}"
        )
        print(
            f"{'bomb':30} {'file':>10} {'inflates to':>12} {'answer':>6} {'seconds':>8} {'API peak':>11}  message"
        )
        for name, data in bombs.items():
            post("entry.pkl", data)  # untimed: the first of each pays the API's first imports and allocations
            [response], seconds, grown = measured(api.pid, lambda data=data: [post("entry.pkl", data)])  # type: ignore[misc]
            problem = response.json().get("problems", [{"message": response.text}])[0]["message"]
            print(
                f"{name:30} {mib(len(data)):>10} {mib(BOMBS[name].inflates_to):>12} {response.status_code:>6} {seconds:>8.2f}"
                f" {'+' + mib(grown):>11}  {problem[:110]}",
                flush=True,
            )
        names = [name for name in bombs for _ in range(args.copies)]
        with ThreadPoolExecutor(len(names)) as pool:
            responses, seconds, grown = measured(
                api.pid, lambda: list(pool.map(lambda name: post("entry.pkl", bombs[name]), names))
            )
        statuses = sorted({response.status_code for response in responses})
        print(f"all {len(names)} at once: answers {statuses}, {seconds:.2f} s, API peak +{mib(grown)}")
        answer, sent, ms = answered_before_the_body(url)
        print(
            f"wrong token, {mib(DECLARED_BYTES)} declared: {answer.split(b' ', 2)[1].decode()} after {ms:.1f} ms, "
            f"with {sent:,} bytes of the body sent"
        )


if __name__ == "__main__":
    main()
