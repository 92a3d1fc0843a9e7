"""The service end to end: a submission from POST to its leaderboard row, and the API's latency per route.

For each backend (embedded: SQLite + SQLite broker; services: PostgreSQL + Redis) and each worker size
(1 and 2 scoring processes), on a fresh database with the split's metric cache already built:
- POST one submission of every token with --seeds seeds (every metric version is always scored), then time
  until it is scored (GET /submissions/{id}) and until its row is on the leaderboard (GET /leaderboard, whose
  2 s cache is on as in production), against the engine alone scoring the same tokens, seeds and versions
  with as many processes (`score_seeds`, as the workers call it; warm, one BLAS thread each and at the
  workers' niceness, as the workers run): the service's target is at most SERVICE_TARGET times that;
- with the workers idle, GET /leaderboard at a fixed rate from an open-loop client on loopback and report
  p50/p95/p99 latency, measured from each request's scheduled start (a slow answer delays no later request).

With --load N, on each backend with the largest worker size, for --seconds: the public reads the leaderboard
at --rate and its web page at a tenth of that, while a team uploads N entries spread over that time, dry-runs
each (POST /submissions:validate) and polls their status 4 times a second; p50/p95/p99 latency and errors per
route, the load average before and after (other work on the host shows there), how many uploads were still
being scored when the load ended, and a check that every upload was scored exactly once (one row per token,
version and seed; one leaderboard entry per version). The target: the leaderboard at 200/s with
p99 at most 100 ms, the upload routes below 1 s, while 2 workers score on the same 2 cores.

With --storage local,s3: each configuration also with its uploads, its split's scenes and the metric caches in
an S3 object store (moto's server with keep-alive, benchmarks/keepalive_s3.py, started here, or the endpoint
AWS_ENDPOINT_URL names): the split registered from the store, and each worker's caches cold (an earlier worker
published them, each token's and its blocks' packs: it fetches them, and no scene, a token whose cache is in
the store needing none), against the local directory with the cache built.

With --two-stage GROUPS (and --pairs P): a synthetic two-stage split of GROUPS groups, each an original and
its previous frame (stage one) with P synthetic pairs (stage two), scorer.synth.two_stage; navhard's size is
--two-stage 225 --pairs 12 (450 stage-one and 5,400 stage-two tokens). One two-stage upload of every token
(the human trajectories with noise, --seeds seeds) on each backend and worker size: seconds from POST to its
scored status and to its board row (v2.2-two-stage), the CPU seconds of the worker and the API meanwhile, and
the worker's peak RSS, with the load average before and after.

Every run starts with a header that describes the host (benchmarks/host.py). With each worker size it gives
the CPU seconds the worker's and the API's processes used from POST to row, against the engine's (on a host
shared with other work wall times swing, CPU times much less), and the peak RSS (VmHWM) of the worker's
processes: its supervisor, and the others of its session (the scoring consumers and the reaper), read
from /proc just before the worker is stopped. (RUSAGE_CHILDREN would give one maximum over every process this
benchmark ever waited for, API and workers alike.)

With --no-engine the engine-alone reference is skipped (its columns read nan): what the store costs against
the local directory needs only the two services' runs.

Usage: .venv/bin/python benchmarks/service.py [--tokens 2000] [--seeds 1] [--rate 200] [--seconds 10]
       [--backends embedded,services] [--workers 1,2] [--storage local,s3] [--no-engine] [--load 6] [--nice 10]
       [--two-stage 225 --pairs 12]
(Uploads are rate-limited to 30 a minute per token: with --load, keep 2N uploads per minute below that.)
"""

from __future__ import annotations

# isort: off
import scorer  # noqa: F401 - before numpy, so that numpy loads the official results' OpenBLAS kernels

# isort: on
import argparse
import asyncio
import itertools
import math
import multiprocessing
import os
import socket
import sys
import tempfile
import time
import uuid
from collections.abc import Awaitable, Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from functools import cache
from multiprocessing.synchronize import Barrier
from pathlib import Path

import httpx
import numpy as np
from host import host_header
from sqlalchemy import func, select
from threadpoolctl import threadpool_limits

from navsim_lb.processes import api_command, child_process
from scorer.baselines import baseline_submission
from scorer.evaluate import build_split_cache, score_seeds, score_versions
from scorer.geometry import FloatArray
from scorer.scene import scene_paths, scene_start
from scorer.submission import (
    Submission,
    SubmissionMetadata,
    TwoStageSubmission,
    dump_submission_json,
    dump_two_stage_submission_json,
    load_submission,
)
from scorer.synth import synthesize_split
from scorer.synth.two_stage import synthesize_two_stage_split
from scorer.two_stage.split import load_two_stage_split
from scorer.versions import LOG_REPLAY_VERSIONS, TWO_STAGE_VERSIONS
from server.db import make_engine, make_session_factory, transaction
from server.migrate import upgrade
from server.models import Approval, Scope, Summary, TokenResultRow
from server.models import Submission as SubmissionRow
from server.object_store import open_store
from server.runs import split_blocks
from server.services.splits import create_phase, register_split, scene_starts
from server.services.teams import create_team
from server.services.tokens import create_token
from server.settings import Settings, get_settings
from server.shared_caches import publish_caches, publish_packs, scene_hashes
from worker import SCORING_NICENESS
from worker.cli import worker_command

# The throwaway databases and queues come from the tests' helpers: the benchmark runs on the same servers.
sys.path.append(str(Path(__file__).resolve().parent.parent / "tests"))
from scratch import scratch_postgres_database, scratch_redis_queue

DATA = Path(__file__).parent / ".data"
POSTGRES_URL = os.environ.get("NAVSIM_LB_BENCH_POSTGRES", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
REDIS_URL = os.environ.get("NAVSIM_LB_BENCH_REDIS", "redis://127.0.0.1:6379/0")
BUCKET = "navsim-lb-bench"
SPLIT_SEED = 11
CONNECTIONS = 64  # concurrent clients of the leaderboard load
REQUEST_TIMEOUT_S = 30.0
SERVICE_TARGET = 1.25  # POST to leaderboard row against the engine alone
STORE_TARGET = 1.1  # upload to row on the object store (cold worker caches) against the local directory
# How often the client asks whether its upload is scored: each answer costs the API a few ms of the CPU the
# workers score on, so asking 20 times a second would slow what it measures by several percent.
STATUS_POLL_S = 0.25


def synthesized_split(tokens: int) -> Path:
    """Return a synthetic split of `tokens` scenes, built on first use."""
    split = DATA / f"server_split_{tokens}_{SPLIT_SEED}"
    if not (split / "scenes").is_dir():
        started = time.perf_counter()
        synthesize_split(split, tokens, SPLIT_SEED)
        print(f"synthesised {tokens} scenes in {time.perf_counter() - started:.0f} s")
    return split


def prepared_split(tokens: int) -> tuple[Path, Path]:
    """Return a synthetic split of `tokens` scenes and its cache directory, both built on first use."""
    split, cache = synthesized_split(tokens), DATA / f"server_cache_{tokens}_{SPLIT_SEED}"
    started = time.perf_counter()
    failures = build_split_cache(split, cache, list(LOG_REPLAY_VERSIONS), workers=os.cpu_count() or 1)
    assert not failures, failures
    print(f"metric cache ready in {time.perf_counter() - started:.0f} s (built where missing)")
    return split, cache


@cache
def human_trajectories(split: Path) -> dict[str, FloatArray]:
    """Return the split's human trajectories (read from every scene: seconds, once per split)."""
    return baseline_submission(split, "human", "bench").seeds[0]


def entry_file(split: Path, out: Path, seed: int = 0, seeds: int = 1) -> Path:
    """Write a submission of `seeds` seeds (the human trajectories with noise) covering every token of the split."""
    rng = np.random.default_rng(seed)
    human = human_trajectories(split)
    noisy: tuple[dict[str, FloatArray], ...] = tuple(
        {token: poses + rng.normal(0.0, 0.2, poses.shape) for token, poses in human.items()}
        for _ in range(seeds)
    )
    out.write_bytes(dump_submission_json(Submission(SubmissionMetadata(method="bench"), noisy)))
    return out


def prepared_two_stage_split(groups: int, pairs: int) -> tuple[Path, Path]:
    """Return a synthetic two-stage split of `groups` groups of `pairs` synthetic pairs and its cache directory
    (under the two-stage versions), both built on first use."""
    name = f"{groups}x{pairs}_{SPLIT_SEED}"
    split, cache = DATA / f"two_stage_split_{name}", DATA / f"two_stage_cache_{name}"
    if not (split / "scenes").is_dir():
        started = time.perf_counter()
        synthesize_two_stage_split(split, groups, pairs, SPLIT_SEED)
        print(f"synthesised {groups * (2 + 2 * pairs)} scenes in {time.perf_counter() - started:.0f} s")
    started = time.perf_counter()
    failures = build_split_cache(split, cache, list(TWO_STAGE_VERSIONS), workers=os.cpu_count() or 1)
    assert not failures, failures
    print(f"metric cache ready in {time.perf_counter() - started:.0f} s (built where missing)", flush=True)
    return split, cache


def two_stage_entry_file(split: Path, out: Path, seeds: int = 1) -> Path:
    """Write a two-stage submission of `seeds` seeds (the human trajectories with noise) of every token."""
    rng = np.random.default_rng(0)
    human, stages = human_trajectories(split), load_two_stage_split(split)
    noisy = [
        {token: poses + rng.normal(0.0, 0.2, poses.shape) for token, poses in human.items()}
        for _ in range(seeds)
    ]
    first, second = (
        tuple({token: seed[token] for token in tokens} for seed in noisy)
        for tokens in (stages.stage_one_tokens, stages.stage_two_tokens)
    )
    submission = TwoStageSubmission(SubmissionMetadata(method="bench"), first, second)
    out.write_bytes(dump_two_stage_submission_json(submission))
    return out


# What each process of the engine alone scores, set by its initializer: the split, its cache and the entry.
_engine_work: tuple[Path, Path, Submission] | None = None


def _warm_engine_process(barrier: Barrier, split: Path, cache: Path, entry: Path) -> None:
    """Run as a worker's pool process does: one BLAS thread, its niceness; read the entry and score a token
    untimed, then wait for the other processes (a warm worker pays neither imports nor first calls, and the
    engine alone is timed without reading the file)."""
    global _engine_work
    threadpool_limits(1)
    os.nice(SCORING_NICENESS)
    predictions = load_submission(entry.read_bytes(), entry.name)
    score_versions(
        split, cache, predictions.seeds[0], list(LOG_REPLAY_VERSIONS), [next(iter(scene_paths(split)))]
    )
    _engine_work = split, cache, predictions
    barrier.wait()


def _engine_part(tokens: list[str]) -> tuple[int, float]:
    """Score `tokens` of the entry under every version and seed, as one process of the engine alone; return
    how many rows are valid and the CPU seconds it took."""
    assert _engine_work is not None, "run by a pool whose initializer is _warm_engine_process"
    split, cache, predictions = _engine_work
    started = time.process_time()
    rows = score_seeds(split, cache, dict(enumerate(predictions.seeds)), list(LOG_REPLAY_VERSIONS), tokens)
    scored = sum(row.valid for version_rows in rows.values() for row in version_rows)
    return scored, time.process_time() - started


def engine_only(split: Path, cache: Path, entry: Path, processes: int) -> tuple[float, float]:
    """Return the seconds, and the CPU seconds, the engine alone takes to score `entry` (every token, seed and
    version) with `processes` warm processes, each a contiguous part of the tokens, as a run's chunks are."""
    tokens = list(scene_paths(split))
    bounds = [index * len(tokens) // processes for index in range(processes + 1)]
    parts = [tokens[start:stop] for start, stop in itertools.pairwise(bounds)]
    context = multiprocessing.get_context("fork")
    barrier = context.Barrier(processes + 1)
    with context.Pool(processes, _warm_engine_process, (barrier, split, cache, entry)) as pool:
        barrier.wait()
        started = time.perf_counter()
        scored = pool.map(_engine_part, parts, chunksize=1)
        seconds = time.perf_counter() - started
    assert sum(valid for valid, _ in scored), "the engine scored no token"
    return seconds, sum(cpu for _, cpu in scored)


@contextmanager
def backend(kind: str, root: Path) -> Iterator[dict[str, str]]:
    """Yield the environment variables of a fresh database and broker of `kind` under `root`."""
    if kind == "embedded":
        yield {"DATA_DIR": str(root), "QUEUE_NAME": f"navsim-lb-bench-{uuid.uuid4().hex[:8]}"}
        return
    with (
        scratch_postgres_database(POSTGRES_URL, "navsim_lb_bench") as database_url,
        scratch_redis_queue(REDIS_URL, "navsim-lb-bench") as queue,
    ):
        yield {
            "DATA_DIR": str(root),
            "QUEUE_NAME": queue,
            "DATABASE_URL": database_url,
            "BROKER_URL": REDIS_URL,
        }


@contextmanager
def storage(
    kind: str, root: Path, split: Path, cache: Path
) -> Iterator[tuple[dict[str, str], str, int | None]]:
    """Yield the variables of a storage `kind` under `root`, where the split registers from (the local
    directory with its cache built, or an S3 store holding the split's scenes and its published caches, each
    worker's own caches empty) and the pid of the S3 server started here (None for another's)."""
    if kind == "local":
        yield {"CACHE_DIR": str(cache)}, str(split), None
        return
    with ExitStack() as stack:
        own_port = own_pid = None  # of the moto server started here, when no endpoint is given
        if "AWS_ENDPOINT_URL" not in os.environ or os.environ.get("NAVSIM_LB_BENCH_OWN_S3"):
            own_port = port = free_port()
            command = [sys.executable, str(Path(__file__).parent / "keepalive_s3.py"), str(port)]
            own_pid = stack.enter_context(child_process(command, dict(os.environ), root / "moto.log")).pid
            os.environ["NAVSIM_LB_BENCH_OWN_S3"] = "1"  # the next configuration starts its own again
            os.environ |= {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "bench"}
            os.environ |= {"AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"}
        # The tests' helpers, imported once the endpoint is set (they default it to CI's server otherwise).
        from object_stores import make_bucket, port_answers

        if own_port is not None:
            wait_until(lambda: port_answers(port), timeout=60)
        make_bucket(BUCKET)
        location = f"s3://{BUCKET}/bench-{uuid.uuid4().hex[:8]}"
        scenes = open_store(f"{location}/split/scenes")
        for path in scene_paths(split).values():
            scenes.put_bytes(path.name, path.read_bytes())
        # What the workers of an earlier run published: each token's cache, and the packs of the split's blocks.
        caches, hashes = open_store(f"{location}/metric-cache"), scene_hashes(split)
        publish_caches(caches, cache, hashes)
        starts = {token: scene_start(path) for token, path in scene_paths(split).items()}
        publish_packs(caches, cache, hashes, split_blocks(starts))
        os.environ["DATA_DIR"] = str(root / "organiser")  # where registering copies the split
        get_settings.cache_clear()
        variables = {key: os.environ[key] for key in os.environ if key.startswith("AWS_")}
        yield (
            variables | {"STORAGE_URL": location, "CACHE_DIR": str(root / "cold-cache")},
            f"{location}/split",
            own_pid,
        )


def set_up(database_url: str, split: Path | str) -> tuple[str, float]:
    """Migrate, register the split (no baselines: nothing may compete) with its index of log frames, open a
    phase; return a team token and the seconds the index took.

    The index (`scene_starts`) is built once per split, by the first run on it, like the metric cache: a
    board's submissions find both ready, and so does the one timed here (what the first run pays is apart).
    """
    upgrade(database_url)
    engine = make_engine(database_url)
    with transaction(make_session_factory(engine)) as session:
        registered = register_split(session, "bench", split)
        started = time.perf_counter()
        scene_starts(session, registered)
        index_s = time.perf_counter() - started
        create_phase(session, "bench", registered)
        team = create_team(session, "bench-team", [], "", Approval.approved)
        _, token = create_token(session, Scope.team, team, "bench")
    engine.dispose()
    return token, index_s


def wait_until(condition: Callable[[], bool], timeout: float = 600.0, poll_s: float = 0.05) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError("the service did not get there in time")
        time.sleep(poll_s)


def post_to_row(
    client: httpx.Client, entry: Path, versions: tuple[str, ...] = LOG_REPLAY_VERSIONS
) -> tuple[float, float]:
    """POST the entry; return seconds until it is scored and until its row is on the board of each of
    `versions` (the split's)."""
    started = time.perf_counter()
    response = client.post("/api/v1/submissions", files={"file": (entry.name, entry.read_bytes())})
    assert response.status_code == 202, response.text
    submission_id = response.json()["id"]
    wait_until(
        lambda: client.get(f"/api/v1/submissions/{submission_id}").json()["status"] in ("scored", "failed"),
        poll_s=STATUS_POLL_S,
    )
    scored = time.perf_counter() - started
    state = client.get(f"/api/v1/submissions/{submission_id}").json()
    assert state["status"] == "scored", state["error"]

    def on_board() -> bool:
        rows = [client.get("/api/v1/leaderboard", params={"version": v}).json()["rows"] for v in versions]
        return all(any(row["submission_id"] == submission_id for row in board) for board in rows)

    wait_until(on_board)
    return scored, time.perf_counter() - started


@dataclass
class Latencies:
    """What one route answered under load: each answer's latency (seconds from its schedule) and the errors."""

    seconds: list[float] = field(default_factory=list)
    errors: int = 0

    def text(self) -> str:
        if not self.seconds:
            return f"no answer ({self.errors} errors)"
        p50, p95, p99 = np.percentile(np.array(self.seconds) * 1000, [50, 95, 99])
        return f"p50 {p50:.1f} ms, p95 {p95:.1f} ms, p99 {p99:.1f} ms ({len(self.seconds)} answered, {self.errors} errors)"


class Connection:
    """One requester's own HTTP/1.1 connection, kept alive, for GETs; and the shared httpx client for uploads.

    The GETs are written and read by hand: httpx spent about 3.4 ms of the client's CPU per request against
    the API's 0.9 ms, so on a shared host the load client, not the API, fell behind its schedule (and charged
    the API for it). Bodies come with a Content-Length: uvicorn sends one for every answer here.
    """

    def __init__(self, url: str, token: str | None, http: httpx.AsyncClient) -> None:
        address = httpx.URL(url)
        self.host, self.port, self.http = address.host, address.port or 80, http
        self.head = f"Host: {self.host}:{self.port}\r\n" + (
            f"Authorization: Bearer {token}\r\n" if token else ""
        )
        self.streams: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None

    async def get(self, target: str) -> int:
        """GET `target`; return the status code (the body is read and dropped)."""
        if self.streams is None:
            self.streams = await asyncio.open_connection(self.host, self.port)
        reader, writer = self.streams
        try:
            writer.write(f"GET {target} HTTP/1.1\r\n{self.head}\r\n".encode())
            head = (await reader.readuntil(b"\r\n\r\n")).decode("latin-1").lower()
            length = next((line for line in head.split("\r\n") if line.startswith("content-length:")), None)
            if length is None:
                raise ValueError(f"an answer to {target} without a Content-Length")
            await reader.readexactly(int(length.split(":", 1)[1]))
        except (OSError, ValueError, asyncio.IncompleteReadError):
            self.close()
            raise
        if "connection: close" in head:
            self.close()
        return int(head.split(" ", 2)[1])

    def close(self) -> None:
        if self.streams is not None:
            self.streams[1].close()
            self.streams = None


# A request of a route, given a connection and the request's index; it returns the status code.
Send = Callable[[Connection, int], Awaitable[int]]


@dataclass(frozen=True)
class Stream:
    """Requests of one route, sent open-loop at `rate` per second by `connections` requesters."""

    route: str
    send: Send
    rate: float
    connections: int
    expected: int = 200
    team: bool = False  # sent with the team's token


def board_streams(rate: float) -> list[Stream]:
    """The public's reads: the leaderboard's JSON at `rate`, its web page at a tenth of that."""

    async def board(connection: Connection, _: int) -> int:
        return await connection.get("/api/v1/leaderboard?version=v1.1")

    async def page(connection: Connection, _: int) -> int:
        return await connection.get("/")

    return [
        Stream("GET /api/v1/leaderboard", board, rate, CONNECTIONS),
        Stream("GET / (the board's page)", page, rate / 10, CONNECTIONS // 8),
    ]


def upload_streams(entries: list[bytes], seconds: float, ids: list[int]) -> list[Stream]:
    """A team's uploads of `entries` spread over `seconds` (their ids appended to `ids`), as many dry runs
    of them, and the team asking for its uploads' status 4 times a second."""
    rate = len(entries) / seconds

    async def upload(connection: Connection, index: int) -> int:
        files = {"file": (f"entry-{index}.json", entries[index])}
        response = await connection.http.post("/api/v1/submissions", files=files)
        if response.status_code == 202:
            ids.append(response.json()["id"])
        return response.status_code

    async def dry_run(connection: Connection, index: int) -> int:
        files = {"file": (f"entry-{index}.json", entries[index])}
        return (await connection.http.post("/api/v1/submissions:validate", files=files)).status_code

    async def status(connection: Connection, index: int) -> int:
        if not ids:  # nothing uploaded yet: the list of the team's submissions
            return await connection.get("/api/v1/submissions")
        return await connection.get(f"/api/v1/submissions/{ids[index % len(ids)]}")

    return [
        Stream("POST /api/v1/submissions", upload, rate, len(entries), expected=202, team=True),
        Stream("POST /api/v1/submissions:validate", dry_run, rate, len(entries), team=True),
        Stream("GET /api/v1/submissions/{id}", status, 4.0, 4, team=True),
    ]


async def route_latencies(
    url: str, token: str, streams: list[Stream], seconds: float
) -> dict[str, Latencies]:
    """Send every stream open-loop for `seconds`; return each route's latencies.

    A stream's requesters take its requests in schedule order, each sent at its scheduled time or as soon as
    a requester is free; latency counts from the schedule, so a slow server is charged for the wait as well.
    (One task per request would make the client itself the bottleneck once thousands wait for a connection.)
    """
    measured = {stream.route: Latencies() for stream in streams}
    headers = {"Authorization": f"Bearer {token}"}
    async with httpx.AsyncClient(base_url=url, timeout=60, headers=headers) as http:
        start = time.perf_counter() + 0.2

        async def requester(stream: Stream, schedule: Iterator[int]) -> None:
            latencies = measured[stream.route]
            connection = Connection(url, token if stream.team else None, http)
            for index in schedule:
                scheduled = start + index / stream.rate
                await asyncio.sleep(max(0.0, scheduled - time.perf_counter()))
                try:
                    status = await asyncio.wait_for(stream.send(connection, index), REQUEST_TIMEOUT_S)
                except (httpx.HTTPError, OSError, ValueError, asyncio.IncompleteReadError, TimeoutError):
                    connection.close()
                    latencies.errors += 1
                    continue
                if status != stream.expected:
                    latencies.errors += 1
                    continue
                latencies.seconds.append(time.perf_counter() - scheduled)
            connection.close()

        requesters = []
        for stream in streams:
            schedule = iter(range(int(stream.rate * seconds)))
            requesters += [requester(stream, schedule) for _ in range(stream.connections)]
        await asyncio.gather(*requesters)
    return measured


def session_processes(leader: int) -> dict[int, tuple[list[str], list[str]]]:
    """Return pid -> (the fields of /proc/pid/stat after the name, the lines of /proc/pid/status) of the running
    processes of `leader`'s session (a worker: its supervisor, consumers and reaper); empty without /proc."""
    processes = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[3]) != leader:  # the session's leader
                continue
            processes[int(stat.parent.name)] = (fields, (stat.parent / "status").read_text().splitlines())
        except (OSError, ValueError, IndexError):  # gone meanwhile
            continue
    return processes


def session_cpu_seconds(leader: int) -> float:
    """Return the CPU seconds (user and system) the running processes of `leader`'s session have used."""
    ticks = sum(int(fields[11]) + int(fields[12]) for fields, _ in session_processes(leader).values())
    return ticks / os.sysconf("SC_CLK_TCK")


def worker_peak_rss(worker_pid: int) -> tuple[float, list[float]] | None:
    """Return the peak RSS (VmHWM) in MiB of a running worker's main process and, largest first, of the other
    processes of its session (consumers, reaper); None where there is no /proc."""
    peaks: dict[int, float] = {}
    for pid, (_, status) in session_processes(worker_pid).items():
        kib = next((line.split()[1] for line in status if line.startswith("VmHWM:")), None)
        if kib is not None:
            peaks[pid] = int(kib) / 1024
    if worker_pid not in peaks:
        return None
    return peaks.pop(worker_pid), sorted(peaks.values(), reverse=True)


def peak_rss_text(peaks: tuple[float, list[float]] | None) -> str:
    if peaks is None:
        return "n/a (no /proc)"
    main, others = peaks
    return f"supervisor {main:.0f}, consumers and reaper {' '.join(f'{peak:.0f}' for peak in others)}"


@dataclass(frozen=True)
class Running:
    """A service on a fresh backend: API and worker processes (each the leader of its session)."""

    root: Path  # scratch directory
    url: str
    token: str  # a team's
    client: httpx.Client  # with that token
    database_url: str
    worker_pid: int
    api_pid: int
    index_s: float  # what the split's index of log frames took at set-up (a first run on the split pays it)
    store_pid: int | None  # the S3 server's started here, which runs on the same cores

    def store_cpu_seconds(self) -> float:
        """Return the CPU seconds the S3 server started here has used (0 without one)."""
        return session_cpu_seconds(self.store_pid) if self.store_pid else 0.0

    def cpu_seconds(self) -> float:
        """Return the CPU seconds its worker's and API's processes have used (the database's are apart)."""
        return session_cpu_seconds(self.worker_pid) + session_cpu_seconds(self.api_pid)


@contextmanager
def running(
    kind: str, workers: int, split: Path, cache: Path, nice: int, stored: str = "local"
) -> Iterator[Running]:
    """Run API and worker (its consumers `nice` below it) on a fresh backend and storage for the block."""
    with tempfile.TemporaryDirectory(prefix="navsim-lb-bench-") as tmp, ExitStack() as stack:
        root = Path(tmp)
        files, location, store_pid = stack.enter_context(storage(stored, root, split, cache))
        variables = stack.enter_context(backend(kind, root)) | files
        env = {**os.environ, **variables}
        database_url = Settings(**variables).database_url  # type: ignore[arg-type]  # keys are the aliases
        token, index_s = set_up(database_url, location)
        worker_log = root / "worker.log"
        worker = stack.enter_context(
            child_process(worker_command(workers, reaper=True, nice=nice), env, worker_log)
        )
        port = free_port()
        api = stack.enter_context(child_process(api_command("127.0.0.1", port), env, root / "api.log"))
        url = f"http://127.0.0.1:{port}"
        client = stack.enter_context(
            httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=60)
        )
        wait_until(lambda: answers(client), timeout=60)
        wait_until(lambda: "ready." in worker_log.read_text(errors="replace"), timeout=60)
        yield Running(root, url, token, client, database_url, worker.pid, api.pid, index_s, store_pid)


@dataclass(frozen=True)
class Measured:
    scored: float  # seconds from POST to its scored status
    on_board: float  # and to its leaderboard row
    cpu: float  # CPU seconds the worker and the API used meanwhile
    store_cpu: float  # and the S3 server started here, on the same cores
    index_s: float  # Running's
    latency: Latencies | None  # of the leaderboard, if asked
    peaks: tuple[float, list[float]] | None  # worker_peak_rss's


def measure(
    kind: str,
    workers: int,
    split: Path,
    cache: Path,
    entry: Path,
    latency_load: tuple[float, float] | None,
    nice: int,
    stored: str = "local",
    versions: tuple[str, ...] = LOG_REPLAY_VERSIONS,
) -> Measured:
    """Run one configuration on a fresh backend and storage: POST-to-row times of `entry` (its rows on the
    boards of `versions`) and the CPU they took, then leaderboard latency if asked, and the worker's peak RSS."""
    with running(kind, workers, split, cache, nice, stored) as service:
        cpu, store_cpu = service.cpu_seconds(), service.store_cpu_seconds()
        scored, on_board = post_to_row(service.client, entry, versions)
        cpu, store_cpu = service.cpu_seconds() - cpu, service.store_cpu_seconds() - store_cpu
        latency = None
        if latency_load:
            rate, seconds = latency_load
            board = board_streams(rate)[0]
            latency = asyncio.run(route_latencies(service.url, service.token, [board], seconds))[board.route]
        peaks = worker_peak_rss(service.worker_pid)
        return Measured(scored, on_board, cpu, store_cpu, service.index_s, latency, peaks)


def scored_once(database_url: str, submission_ids: list[int], tokens: int, seeds: int) -> list[str]:
    """Return what is wrong with each submission's record: not scored, rows missing or doubled, entries."""
    engine = make_engine(database_url)
    problems = []
    with make_session_factory(engine)() as session:
        for submission_id in submission_ids:
            submission = session.get(SubmissionRow, submission_id)
            rows = session.scalar(select(func.count()).where(TokenResultRow.submission_id == submission_id))
            entries = session.scalar(select(func.count()).where(Summary.submission_id == submission_id))
            if submission is None or submission.status != "scored":
                problems.append(f"{submission_id}: {submission.status if submission else 'missing'}")
            elif rows != tokens * seeds * len(LOG_REPLAY_VERSIONS) or entries != len(LOG_REPLAY_VERSIONS):
                problems.append(f"{submission_id}: {rows} rows, {entries} leaderboard entries")
    engine.dispose()
    return problems


@dataclass(frozen=True)
class Loaded:
    """The service under load: each route's latencies, the load average before and after, how many uploads
    were still being scored when the load ended, the seconds until all were and the CPU seconds its worker's
    processes used meanwhile (on a shared host they swing far less), what is wrong with their records, and
    the worker's peak RSS."""

    latencies: dict[str, Latencies]
    load_average: tuple[tuple[float, float, float], tuple[float, float, float]]
    unscored_at_end: int
    total_s: float
    worker_cpu_s: float
    problems: list[str]
    peaks: tuple[float, list[float]] | None


def under_load(
    kind: str,
    workers: int,
    split: Path,
    cache: Path,
    uploads: int,
    seeds: int,
    rate: float,
    seconds: float,
    nice: int,
) -> Loaded:
    """Read the board at `rate` (and its page) for `seconds` while a team uploads `uploads` submissions,
    spread over that time, dry-runs them and polls their status; then wait until all are scored."""
    with running(kind, workers, split, cache, nice) as service:
        entries = [
            entry_file(split, service.root / f"entry-{index}.json", seed=index, seeds=seeds).read_bytes()
            for index in range(uploads)
        ]
        ids: list[int] = []
        streams = board_streams(rate) + upload_streams(entries, seconds, ids)
        before = os.getloadavg()
        started, worker_cpu = time.perf_counter(), session_cpu_seconds(service.worker_pid)
        latencies = asyncio.run(route_latencies(service.url, service.token, streams, seconds))
        after = os.getloadavg()
        client = service.client
        unscored = lambda: sum(
            client.get(f"/api/v1/submissions/{i}").json()["status"] not in ("scored", "failed") for i in ids
        )
        unscored_at_end = unscored()
        wait_until(lambda: unscored() == 0, timeout=3600, poll_s=1.0)
        return Loaded(
            latencies,
            (before, after),
            unscored_at_end,
            time.perf_counter() - started,
            session_cpu_seconds(service.worker_pid) - worker_cpu,
            scored_once(service.database_url, ids, split_size(split), seeds),
            worker_peak_rss(service.worker_pid),
        )


def split_size(split: Path) -> int:
    return len(list((split / "scenes").iterdir()))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--tokens", type=int, default=2000)
    parser.add_argument("--seeds", type=int, default=1, help="seeds of each upload (navtest entries have 3)")
    parser.add_argument("--rate", type=float, default=200.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--backends", default="embedded,services")
    parser.add_argument("--workers", default="1,2")
    parser.add_argument("--load", type=int, default=0, help="uploads scored while the leaderboard is read")
    parser.add_argument(
        "--nice", type=int, default=SCORING_NICENESS, help="the workers' `navsim-lb worker --nice`"
    )
    parser.add_argument("--storage", default="local", help="local,s3: uploads, scenes and caches where")
    parser.add_argument(
        "--no-engine", action="store_true", help="skip the engine-alone reference (storage ratios only)"
    )
    parser.add_argument("--two-stage", type=int, default=0, help="groups of a two-stage split (navhard: 225)")
    parser.add_argument("--pairs", type=int, default=12, help="synthetic pairs of each two-stage group")
    args = parser.parse_args()
    print("\n".join(host_header()), flush=True)  # before any thread or process starts (host.py says why)

    sizes = [int(n) for n in args.workers.split(",")]
    if args.two_stage:
        two_stage(args.two_stage, args.pairs, args.seeds, args.backends.split(","), sizes, args.nice)
        return
    split, cache = prepared_split(args.tokens)
    if args.load:
        for kind in args.backends.split(","):
            loaded = under_load(
                kind, max(sizes), split, cache, args.load, args.seeds, args.rate, args.seconds, args.nice
            )
            before, after = (" ".join(f"{value:.2f}" for value in load) for load in loaded.load_average)
            print(
                f"{kind}: {args.seconds:.0f} s of GET /leaderboard at {args.rate:.0f}/s (and its page at a tenth)"
                f" while a team uploaded {args.load} entries of {args.tokens} tokens x {args.seeds} seeds, dry-ran"
                f" them and polled them, scored by {max(sizes)} worker processes at niceness {args.nice}; load"
                f" average {before} before, {after} after; {loaded.unscored_at_end} uploads still being scored"
                " when the load ended:",
                flush=True,
            )
            for route, latencies in loaded.latencies.items():
                print(f"  {route:34} {latencies.text()}")
            print(
                f"  all scored after {loaded.total_s:.0f} s, the worker's CPU meanwhile {loaded.worker_cpu_s:.1f} s; "
                + (
                    "every upload scored exactly once"
                    if not loaded.problems
                    else f"PROBLEMS: {loaded.problems}"
                )
                + f"; worker peak RSS (MiB): {peak_rss_text(loaded.peaks)}",
                flush=True,
            )
        return
    entry = entry_file(split, DATA / f"entry_{args.tokens}_{SPLIT_SEED}_{args.seeds}.json", seeds=args.seeds)
    engine = {
        workers: (math.nan, math.nan) if args.no_engine else engine_only(split, cache, entry, workers)
        for workers in sizes
    }
    print(
        f"{args.tokens} tokens x {args.seeds} seeds, the board's metric versions ({', '.join(LOG_REPLAY_VERSIONS)}): seconds from"
        " POST to its scored status and to its leaderboard row, against the engine alone on as many processes"
        f" (target: at most {SERVICE_TARGET}x); CPU seconds of the worker and the API meanwhile, against the"
        " engine's (what a host shared with other work still measures), and of the S3 server started here (moto,"
        " on the same cores: a store of its own host costs the workers none); the split's index of log frames,"
        " which the first run on a split builds:"
    )
    print(
        f"{'backend':10} {'storage':>7} {'workers':>7} {'scored':>8} {'on board':>9} {'engine':>7} {'ratio':>6}"
        f" {'CPU':>7} {'engine':>7} {'ratio':>6} {'store':>6} {'index':>6}  worker peak RSS (MiB)"
    )
    latencies = {}
    on_board: dict[tuple[str, int, str], float] = {}
    for kind, stored, workers in itertools.product(args.backends.split(","), args.storage.split(","), sizes):
        # Leaderboard latency once per backend, with the largest worker idle beside the API.
        load = (args.rate, args.seconds) if workers == max(sizes) and stored == "local" else None
        measured = measure(kind, workers, split, cache, entry, load, args.nice, stored)
        seconds, cpu = engine[workers]
        print(
            f"{kind:10} {stored:>7} {workers:>7} {measured.scored:>8.1f} {measured.on_board:>9.1f} {seconds:>7.1f}"
            f" {measured.on_board / seconds:>5.2f}x {measured.cpu:>7.1f} {cpu:>7.1f}"
            f" {measured.cpu / cpu:>5.2f}x {measured.store_cpu:>6.1f} {measured.index_s:>6.1f}"
            f"  {peak_rss_text(measured.peaks)}",
            flush=True,
        )
        if measured.latency is not None:
            latencies[kind] = measured.latency
        on_board[kind, workers, stored] = measured.on_board
    for (kind, workers, stored), seconds in on_board.items():
        if stored == "s3" and (kind, workers, "local") in on_board:
            print(
                f"{kind}, {workers} workers: upload-to-row on the S3 store (cold worker caches) / on the local"
                f" directory: {seconds / on_board[kind, workers, 'local']:.2f}x (target {STORE_TARGET}x)"
            )
    for kind, latency in latencies.items():
        print(f"GET /leaderboard {kind}: {args.rate:.0f}/s for {args.seconds:.0f} s: {latency.text()}")


def two_stage(groups: int, pairs: int, seeds: int, backends: list[str], sizes: list[int], nice: int) -> None:
    """Time a two-stage upload of a synthetic two-stage split from POST to its board row (--two-stage)."""
    split, cache = prepared_two_stage_split(groups, pairs)
    entry = two_stage_entry_file(
        split, DATA / f"two_stage_entry_{groups}x{pairs}_{SPLIT_SEED}_{seeds}.json", seeds
    )
    print(
        f"two-stage split of {groups} groups x {pairs} synthetic pairs ({2 * groups} stage-one and"
        f" {2 * groups * pairs} stage-two tokens) x {seeds} seeds, {', '.join(TWO_STAGE_VERSIONS)}, metric cache"
        " built: seconds from POST to its scored status and to its board row; CPU seconds of the worker and the"
        " API meanwhile; load average before and after:"
    )
    print(
        f"{'backend':10} {'workers':>7} {'scored':>8} {'on board':>9} {'CPU':>8} {'CPU-ms/token':>12}"
        f" {'load before':>16} {'load after':>16}  worker peak RSS (MiB)"
    )
    tokens = 2 * groups * (1 + pairs) * seeds
    for kind, workers in itertools.product(backends, sizes):
        before = os.getloadavg()
        measured = measure(kind, workers, split, cache, entry, None, nice, versions=TWO_STAGE_VERSIONS)
        after = os.getloadavg()
        loads = [" ".join(f"{value:.2f}" for value in load) for load in (before, after)]
        print(
            f"{kind:10} {workers:>7} {measured.scored:>8.1f} {measured.on_board:>9.1f} {measured.cpu:>8.1f}"
            f" {1000 * measured.cpu / tokens:>12.1f} {loads[0]:>16} {loads[1]:>16}  {peak_rss_text(measured.peaks)}",
            flush=True,
        )


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def answers(client: httpx.Client) -> bool:
    """Whether the API answers its health check with 200."""
    try:
        return client.get("/api/v1/health").status_code == 200
    except httpx.HTTPError:
        return False


if __name__ == "__main__":
    main()
