"""What a chunk scores: its run as a job, the tokens still without rows, and the run's trajectories.

A redelivered or re-dispatched chunk scores only the tokens missing from the rows; the tokens written
already still pair with the rest for v2.2's two-frame comfort, as the chunk's context does.

A process keeps the trajectories it read last (`trajectories`): every chunk of a run scores the same file.
It reads them from the copy the upload's check parsed (server.storage): parsing a navtest-size file again
(12,000 tokens x 3 seeds) costs as much as scoring a chunk.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache

from sqlalchemy.orm import Session

from scorer.geometry import FloatArray
from server.models import FailureKind, SplitKind, Submission
from server.object_store import ObjectStore
from server.runs._chunks import ChunkStart
from server.runs._plan import token_blocks
from server.runs._run import completed_tokens, run_versions
from server.services.errors import NotFound
from server.split_store import split_stages, split_tokens
from server.storage import read_file, read_trajectories

MAX_LISTED_PROBLEMS = 5
# Parsed files a process keeps: the run it scores, and one more for the chunks of two runs interleaving.
PARSED_FILES_KEPT = 2


class Rejected(Exception):
    """A run that cannot go on: `message` is shown to the team, `detail` only to admins."""

    def __init__(self, kind: FailureKind, message: str, detail: str | None = None) -> None:
        super().__init__(message)
        self.kind, self.message, self.detail = kind, message, detail

    def __reduce__(self) -> tuple[type[Rejected], tuple[FailureKind, str, str | None]]:
        # Raised in an isolated child (worker.isolated), it travels to its parent pickled.
        return Rejected, (self.kind, self.message, self.detail)


@dataclass(frozen=True)
class ScoringJob:
    """Everything a worker needs to score one run of a submission but the file's bytes, stored under
    `stored_name`, and the split's tokens: both are large, and read only when the file is parsed."""

    submission_id: int
    run: int
    filename: str
    stored_name: str
    sha256: str  # of the upload: the stored bytes must still match it
    split_name: str
    split_source: str  # a directory, or an object store's prefix (server.split_store)
    split_hash: str
    split_kind: SplitKind
    seed_count: int
    versions: tuple[str, ...]


@dataclass(frozen=True)
class ChunkInputs:
    """A chunk taken by its process: the run's job, the tokens to write and the tokens scored beside them."""

    chunk_id: int
    job: ScoringJob
    todo: tuple[str, ...]  # the chunk's tokens without every row
    context: tuple[str, ...]  # scored for EC to pair with, not written
    isolated: bool  # one token with a death on record: scored in a process of its own (worker.isolated)
    # The blocks of the split it holds whole (server.runs._plan): their metric caches are fetched as packs.
    packs: tuple[tuple[str, ...], ...] = ()
    # How the isolated process scoring its one token died: the token is written as failed, not scored.
    process_death: str | None = None


def load_job(session: Session, submission_id: int) -> ScoringJob:
    """Return the current run of a submission as a scoring job (its file named, not read)."""
    submission = session.get(Submission, submission_id)
    if submission is None:
        raise NotFound(f"submission {submission_id} does not exist")
    split = submission.split
    return ScoringJob(
        submission_id=submission.id,
        run=submission.run,
        filename=submission.filename,
        stored_name=submission.stored_name,
        sha256=submission.sha256,
        split_name=split.name,
        split_source=split.directory,
        split_hash=split.content_hash,
        split_kind=SplitKind(split.kind),
        seed_count=submission.seed_count,
        versions=run_versions(split),
    )


def chunk_inputs(
    session: Session, submission_id: int, run: int, start: ChunkStart, packs: bool = False
) -> ChunkInputs | None:
    """Return what the chunk `start` took has left to score; None when the run is no longer wanted. With
    `packs` (the metric caches come from an object store), the blocks it holds whole as well."""
    done = completed_tokens(session, submission_id, run, among=start.tokens)
    if done is None:
        return None
    todo = tuple(token for token in start.tokens if token not in done)
    job = load_job(session, submission_id)
    return ChunkInputs(
        chunk_id=start.chunk_id,
        job=job,
        todo=todo,
        context=(*start.context, *(token for token in start.tokens if token in done)),
        isolated=start.isolated and bool(todo),
        packs=_whole_blocks(session, submission_id, {*start.tokens, *start.context}) if packs else (),
    )


def _whole_blocks(session: Session, submission_id: int, tokens: set[str]) -> tuple[tuple[str, ...], ...]:
    """Return the blocks of the split (`token_blocks`) whose every token is among `tokens`."""
    submission = session.get(Submission, submission_id)
    assert submission is not None  # load_job found it
    blocks = token_blocks(session, submission.split)
    held = dict.fromkeys(blocks[token] for token in tokens if token in blocks)
    return tuple(block for block in held if tokens.issuperset(block))


def _stored_file(job: ScoringJob, store: ObjectStore) -> bytes:
    """Return the stored bytes of the run's file, or raise Rejected when they are missing or damaged (an
    unreachable store raises StoreUnavailable: the chunk waits for it)."""
    where = f"{job.stored_name} in {store.url}"
    try:
        data = read_file(store, job.stored_name)
    except FileNotFoundError:
        raise Rejected(
            FailureKind.infrastructure,
            "the stored copy of this file is missing",
            f"submission {job.submission_id}: no {where}; restore it, or ask the team to upload it again",
        ) from None
    if hashlib.sha256(data).hexdigest() != job.sha256:
        raise Rejected(
            FailureKind.infrastructure,
            "the stored copy of this file is damaged (its sha256 differs from the upload)",
            f"submission {job.submission_id}: {where} does not hash to {job.sha256}; restore it, or ask the "
            "team to upload it again",
        )
    return data


@lru_cache(maxsize=PARSED_FILES_KEPT)
def trajectories(job: ScoringJob, store: ObjectStore) -> tuple[dict[str, FloatArray], ...]:
    """Return each seed's trajectories of the run, or raise Rejected when its stored file is missing, damaged or
    no longer fits the split. A run's file is checked and read once per process; an error is raised again each
    time.

    The trajectories come from the copy its upload's check parsed; without one (an upload stored before those
    copies, or a copy lost) the file is parsed again.
    """
    # Imported here: the API imports this package, and loads the parser only when it checks an upload.
    from scorer.submission import coverage_problems
    from server.services.errors import Invalid
    from server.services.validation import read_upload

    data = _stored_file(job, store)
    # A two-stage split's mapping lists its tokens.
    two_stage = job.split_kind == SplitKind.two_stage
    stages = split_stages(job.split_source, job.split_hash) if two_stage else None
    tokens = (
        [*stages.stage_one_tokens, *stages.stage_two_tokens]
        if stages
        else list(split_tokens(job.split_source, job.split_hash))
    )
    seeds = read_trajectories(store, job.stored_name, job.sha256)
    if seeds is None:
        try:
            seeds = read_upload(data, job.filename, tokens, stages)[1]
        except Invalid as error:
            listed = "; ".join(problem["message"] or "" for problem in error.problems[:MAX_LISTED_PROBLEMS])
            raise Rejected(FailureKind.submission, f"the file cannot be read: {listed}") from None
    problems = coverage_problems([list(seed) for seed in seeds], tokens)
    if problems:
        # The file was checked against the split at upload: the split's tokens changed since.
        raise Rejected(
            FailureKind.infrastructure,
            f"split {job.split_name} changed after the upload; the file no longer matches it",
            "; ".join(str(problem) for problem in problems[:MAX_LISTED_PROBLEMS]),
        )
    return seeds
