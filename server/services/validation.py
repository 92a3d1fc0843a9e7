"""Synchronous validation of an uploaded submission file with the engine's own loader (scorer.submission)."""

from __future__ import annotations

import hashlib
import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import PurePath
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

from server.numbers import counted
from server.services.errors import Invalid

if TYPE_CHECKING:
    from scorer.submission import ByteSource, Submission, SubmissionFile, TwoStageSubmission
    from scorer.two_stage.split import TwoStageSplit
    from server.object_store import Staged

# Metadata a team may give in the file or (all but the email) as form fields (form fields win).
METADATA_FIELDS = ("method", "authors", "email", "institution", "country", "tech_report_url", "code_url")
FORM_METADATA_FIELDS = tuple(field for field in METADATA_FIELDS if field != "email")
URL_FIELDS = ("tech_report_url", "code_url")  # shown as links on the leaderboard: web addresses only


@dataclass(frozen=True)
class ValidUpload:
    """A submission file that passed every check, with what the server stores about it: its bytes (`data`),
    or, for a file streamed to the store as it was checked, the object written (`staged`, named at commit)."""

    data: bytes | None
    filename: str
    sha256: str
    seed_count: int
    token_count: int
    metadata: dict[str, str]
    # Per seed, token -> poses, as the check parsed them (stored beside the file: server.storage).
    trajectories: tuple[dict[str, Any], ...] = ()
    size_bytes: int = 0
    staged: Staged | None = None


class Received:
    """An upload's bytes as the parser reads them: hashed, counted and passed to `sink` (the store's staged
    object) on the way, so that the file flows once; past `max_bytes`, `too_large()` is raised."""

    def __init__(
        self,
        source: ByteSource,
        sink: Callable[[bytes], None] | None = None,
        max_bytes: int | None = None,
        too_large: Callable[[], Exception] = lambda: ValueError("the upload is too large"),
    ) -> None:
        self.source, self.sink, self.max_bytes, self.too_large = source, sink, max_bytes, too_large
        self.hash, self.size = hashlib.sha256(), 0

    def read(self, size: int = -1) -> bytes:
        data = self.source.read(size)
        self.size += len(data)
        if self.max_bytes is not None and self.size > self.max_bytes:
            raise self.too_large()
        self.hash.update(data)
        if self.sink is not None and data:
            self.sink(data)
        return data

    def drain(self) -> None:
        """Read what the parser left (after a gzip stream's or a pickle's end): it is part of the file."""
        while self.read(1 << 20):
            pass


def _problem(problem: Any) -> dict[str, str | None]:
    return {"token": problem.token, "field": problem.field, "message": problem.message}


def _file_metadata(submission: Any) -> dict[str, str]:
    metadata = submission.metadata
    values = {name: getattr(metadata, name, None) for name in METADATA_FIELDS}
    return {name: str(value) for name, value in values.items() if value not in (None, "")}


def _is_web_address(text: str) -> bool:
    parts = urlsplit(text)
    return parts.scheme in ("http", "https") and bool(parts.netloc) and not any(c.isspace() for c in text)


ONE_STAGE_FORM = "a one-stage submission (NAVSIM's pickle with `predictions`, or navsim-lb/submission JSON)"
TWO_STAGE_FORM = (
    "a two-stage submission (NAVSIM v2's pickle with `first_stage_predictions` and `second_stage_predictions`, "
    "or navsim-lb/submission-two-stage JSON)"
)


def _wrong_form(filename: str, stages: TwoStageSplit | None) -> Invalid:
    """Return the refusal of a file in the other split kind's form, saying which form the split takes."""
    two_stage = stages is not None
    expected, found = (TWO_STAGE_FORM, ONE_STAGE_FORM) if two_stage else (ONE_STAGE_FORM, TWO_STAGE_FORM)
    kind = "a two-stage" if two_stage else "a one-stage"
    message = f"{filename}: this phase's split is {kind} split: it takes {expected}; the file is {found}"
    return Invalid(message, [{"token": None, "field": None, "message": message}])


def _reads_as_other_form(read: SubmissionFile, stages: TwoStageSplit | None) -> bool:
    """Whether a file the split's form refused reads in the other kind's form."""
    from scorer.submission import SubmissionError, one_stage, two_stage

    try:
        (one_stage if stages is not None else two_stage)(read)
    except SubmissionError:
        return False
    return True


def _two_stage_problems(submission: TwoStageSubmission, stages: TwoStageSplit) -> list[Any]:
    """Return what keeps a two-stage submission from covering each stage's tokens once per seed."""
    from scorer.submission import MAX_SEEDS, STAGE_FIELDS, Problem, two_stage_coverage_problems

    problems = two_stage_coverage_problems(
        [list(seed) for seed in submission.first_stage],
        [list(seed) for seed in submission.second_stage],
        stages.stage_one_tokens,
        stages.stage_two_tokens,
    )
    if len(submission.first_stage) > MAX_SEEDS:
        message = f"{len(submission.first_stage)} seeds: a submission holds at most {MAX_SEEDS}"
        problems.insert(0, Problem(None, STAGE_FIELDS[0], message))
    return problems


def read_upload(
    source: ByteSource | bytes,
    filename: str,
    split_tokens: Sequence[str],
    stages: TwoStageSplit | None = None,
) -> tuple[Submission | TwoStageSubmission, tuple[dict[str, Any], ...]]:
    """Return the file read in its split's form and, per seed, token -> poses of every token it submits (a
    two-stage file's stage one, then stage two, each in the file's order: the official row order), or raise
    Invalid listing every problem of the file (with its coverage of the split, per stage for a two-stage one,
    where the file names its tokens). `stages` is a two-stage split's mapping, None for a one-stage split.

    The file is read in one pass as `source` streams it (scorer.submission.read_submission_file): this is the
    one place an upload is parsed."""
    from scorer.submission import (
        ContentLimit,
        SubmissionError,
        TwoStageSubmission,
        coverage_problems,
        one_stage,
        read_submission_file,
        two_stage,
        two_stage_coverage_problems,
    )

    # What a valid file of the split can take bounds what it may inflate to (a bomb stops there).
    limit = ContentLimit.for_tokens(split_tokens)
    read = None
    try:
        read = read_submission_file(
            io.BytesIO(source) if isinstance(source, bytes) else source, filename, limit
        )
        submission: Submission | TwoStageSubmission = one_stage(read) if stages is None else two_stage(read)
    except SubmissionError as error:
        if read is not None and _reads_as_other_form(read, stages):
            raise _wrong_form(filename, stages) from None
        if stages is None:
            coverage = coverage_problems(error.seed_tokens, split_tokens)
        else:
            coverage = two_stage_coverage_problems(
                error.seed_tokens, error.second_stage_tokens, stages.stage_one_tokens, stages.stage_two_tokens
            )
        problems = [_problem(p) for p in error.problems + coverage]
        raise Invalid(f"{filename}: {counted(len(problems), 'problem')} in the file", problems) from None
    if isinstance(submission, TwoStageSubmission):
        from scorer.two_stage.score import submitted_rows  # the engine: only for a two-stage file

        return submission, tuple(
            submitted_rows(submission, seed) for seed in range(len(submission.first_stage))
        )
    return submission, submission.seeds


def _split_problems(
    submission: Submission | TwoStageSubmission, split_tokens: Sequence[str], stages: TwoStageSplit | None
) -> list[dict[str, str | None]]:
    """Return what keeps a readable file from covering its split once per seed (per stage for two stages)."""
    from scorer.submission import TwoStageSubmission, validate_submission

    if isinstance(submission, TwoStageSubmission):
        assert stages is not None
        return [_problem(p) for p in _two_stage_problems(submission, stages)]
    return [_problem(p) for p in validate_submission(submission, split_tokens)]


def validate_upload(
    data: bytes,
    filename: str,
    split_tokens: Sequence[str],
    form_metadata: dict[str, str] | None = None,
    stages: TwoStageSplit | None = None,
) -> ValidUpload:
    """Return the checked file, or raise Invalid listing every problem (token, field, message). `stages` is
    a two-stage split's mapping (`read_upload`)."""
    return validate_stream(Received(io.BytesIO(data)), filename, split_tokens, form_metadata, stages, data)


def validate_stream(
    received: Received,
    filename: str,
    split_tokens: Sequence[str],
    form_metadata: dict[str, str] | None = None,
    stages: TwoStageSplit | None = None,
    data: bytes | None = None,
    staged: Staged | None = None,
) -> ValidUpload:
    """Return the checked upload as it streams through `received` (read to its end; `staged` the object its
    sink writes, `data` its bytes when the caller holds them), or raise Invalid listing every problem."""
    filename = PurePath(filename or "submission").name
    submission, seeds = read_upload(received, filename, split_tokens, stages)
    received.drain()
    problems = _split_problems(submission, split_tokens, stages)
    if problems:
        raise Invalid(f"{filename}: {counted(len(problems), 'problem')} against the split", problems)
    metadata = _file_metadata(submission)
    metadata.update(
        {
            k: v.strip()
            for k, v in (form_metadata or {}).items()
            if k in FORM_METADATA_FIELDS and v and v.strip()
        }
    )
    metadata.setdefault("method", PurePath(filename).name.split(".")[0])
    problems += [
        {"token": None, "field": field, "message": f"{field} must be an http:// or https:// address"}
        for field in URL_FIELDS
        if field in metadata and not _is_web_address(metadata[field])
    ]
    if problems:
        raise Invalid(f"{filename}: {counted(len(problems), 'problem')} in the metadata", problems)
    return ValidUpload(
        data=data,
        filename=filename,
        sha256=received.hash.hexdigest(),
        seed_count=len(seeds),
        token_count=len(split_tokens),
        metadata=metadata,
        trajectories=seeds,
        size_bytes=received.size,
        staged=staged,
    )
