"""Synchronous validation of an uploaded submission file with the engine's own loader (scorer.submission)."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import PurePath
from typing import Any
from urllib.parse import urlsplit

from server.services.errors import Invalid

# Metadata a team may give in the file or as form fields (form fields win).
METADATA_FIELDS = ("method", "authors", "email", "institution", "country", "tech_report_url", "code_url")
URL_FIELDS = ("tech_report_url", "code_url")  # shown as links on the leaderboard: web addresses only


@dataclass(frozen=True)
class ValidUpload:
    """A submission file that passed every check, with what the server stores about it."""

    data: bytes
    filename: str
    sha256: str
    seed_count: int
    token_count: int
    metadata: dict[str, str]
    # Per seed, token -> poses, as the check parsed them (stored beside the file: server.storage).
    trajectories: tuple[dict[str, Any], ...] = ()


def _problem(problem: Any) -> dict[str, str | None]:
    return {"token": problem.token, "field": problem.field, "message": problem.message}


def _file_metadata(submission: Any) -> dict[str, str]:
    metadata = submission.metadata
    values = {name: getattr(metadata, name, None) for name in METADATA_FIELDS}
    return {name: str(value) for name, value in values.items() if value not in (None, "")}


def _is_web_address(text: str) -> bool:
    parts = urlsplit(text)
    return parts.scheme in ("http", "https") and bool(parts.netloc) and not any(c.isspace() for c in text)


def validate_upload(
    data: bytes, filename: str, split_tokens: Sequence[str], form_metadata: dict[str, str] | None = None
) -> ValidUpload:
    """Return the checked upload, or raise Invalid listing every problem (token, field, message)."""
    from scorer.submission import (
        ContentLimit,
        SubmissionError,
        coverage_problems,
        load_submission,
        validate_submission,
    )

    filename = PurePath(filename or "submission").name
    try:
        # What a valid file of the split can take bounds what it may inflate to (a bomb stops there).
        submission = load_submission(data, filename, ContentLimit.for_tokens(split_tokens))
    except SubmissionError as error:
        found = error.problems + coverage_problems(error.seed_tokens, split_tokens)
        problems = [_problem(p) for p in found]
        raise Invalid(f"{filename}: {len(problems)} problem(s) in the file", problems) from None
    problems = [_problem(p) for p in validate_submission(submission, split_tokens)]
    if problems:
        raise Invalid(f"{filename}: {len(problems)} problem(s) against the split", problems)
    metadata = _file_metadata(submission)
    metadata.update(
        {k: v.strip() for k, v in (form_metadata or {}).items() if k in METADATA_FIELDS and v and v.strip()}
    )
    metadata.setdefault("method", PurePath(filename).name.split(".")[0])
    problems = [
        {"token": None, "field": field, "message": f"{field} must be an http:// or https:// address"}
        for field in URL_FIELDS
        if field in metadata and not _is_web_address(metadata[field])
    ]
    if problems:
        raise Invalid(f"{filename}: {len(problems)} problem(s) in the metadata", problems)
    return ValidUpload(
        data=data,
        filename=filename,
        sha256=hashlib.sha256(data).hexdigest(),
        seed_count=len(submission.seeds),
        token_count=len(split_tokens),
        metadata=metadata,
        trajectories=submission.seeds,
    )
