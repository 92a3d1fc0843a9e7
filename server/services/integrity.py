"""Integrity checks for organisers: flag entries that copy the hidden logged future, copy another team's
entry, or probe the hidden set (`integrity_checks` has the arithmetic and its thresholds).

A check of a split runs after each run of one of its entries is scored (a worker's task sent once the run is
committed: the run never waits on it nor fails with it), and when an organiser starts one (the admin console,
the admin API), after the request has been answered; never in a team's request. It reads every non-baseline
submission of the split from its stored trajectories, every seed. Its flags, with their evidence, replace the split's previous ones. Flags are shown to organisers
only, and act on nothing: the organiser decides (hide, disqualify) with the usual actions.

Cost on a navtest-size split (12,146 tokens, 3 seeds an entry; `benchmarks/integrity.py`, CPU time on a shared
2-core EPYC): the human futures take 6-35 ms a scene to read (up to 7 min for navtest), once per split and
engine for all workers (server.shared_futures); the leaked-log check 10-15 ms an entry, the near-identical check
5 s for 100 entries (it grows with their square and the seeds'), probing 4 s for 20 teams of 5 uploads; reading
each entry's stored trajectories comes on top.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker

from scorer.geometry import FloatArray
from server.db import transaction
from server.models import ApiToken, IntegrityCheck, IntegrityFlag, Split, Status, Submission, utc_now
from server.services.admin import audit
from server.services.integrity_checks import Entry, Finding, leaked_log, near_duplicates, probing
from server.services.splits import split_tokens
from server.settings import Settings
from server.shared_futures import human_futures
from server.storage import submission_trajectories

log = logging.getLogger(__name__)
POSES = 8
AFTER_COMMIT = timedelta(seconds=5)  # a run's end time to its commit, at most


def _aligned(predictions: dict[str, FloatArray], tokens: list[str]) -> FloatArray:
    """Return positions on the split's tokens (tokens, 8, 2) from token -> poses (8, >= 2), NaN where none."""
    aligned = np.full((len(tokens), POSES, 2), np.nan)
    for index, token in enumerate(tokens):
        poses = predictions.get(token)
        if poses is not None and np.shape(poses)[0] == POSES:
            aligned[index] = np.asarray(poses, dtype=np.float64)[:, :2]
    return aligned


def start_check(session: Session, actor: ApiToken | None, split: Split) -> IntegrityCheck:
    """Record an organiser's check of a split, to be run by `run_check` once the caller has committed."""
    check = _record_check(session, split)
    audit(session, actor, "integrity_check", "split", split.id, split=split.name, check=check.id)
    return check


def _record_check(session: Session, split: Split) -> IntegrityCheck:
    check = IntegrityCheck(split_id=split.id, skipped=[])
    session.add(check)
    session.flush()
    return check


def start_check_after_run(session: Session, submission_id: int) -> IntegrityCheck | None:
    """Record the check of a split after one of its entries was scored (a worker's task, once the run is
    committed), or None where nothing is to check: a baseline, a run not scored (cancelled or re-run since),
    or a check of the split started after this run ended and finished, which read this entry too.

    Idempotent: the task may be delivered twice, and runs that end together share the first check to start
    after them (a run that ends while a check runs gets its own: two may overlap, `complete_check` keeps the
    newer). The margin covers the moment between a run's end
    time and its commit, when a check could not yet see it. A check killed midway stays unfinished, and the
    next one to finish deletes it."""
    submission = session.get(Submission, submission_id)
    if submission is None or submission.is_baseline or submission.status != Status.scored:
        return None
    assert submission.finished_at is not None  # set with the status
    newer = select(IntegrityCheck.id).where(
        IntegrityCheck.split_id == submission.split_id,
        IntegrityCheck.started_at > submission.finished_at + AFTER_COMMIT,
        IntegrityCheck.finished_at.is_not(None),
    )
    if session.scalars(newer).first() is not None:
        return None
    return _record_check(session, submission.split)


def run_check(session_factory: sessionmaker[Session], settings: Settings, check_id: int) -> None:
    """Run a recorded check in a transaction of its own (the API's once its answer is sent, or a worker's)."""
    with transaction(session_factory) as session:
        check = session.get(IntegrityCheck, check_id)
        if check is not None:
            complete_check(session, settings, check)


def complete_check(session: Session, settings: Settings, check: IntegrityCheck) -> None:
    """Read the check's split's entries, store the flags, and drop the split's older checks and their flags
    (or this one, where a newer check finished first: checks after runs may overlap); a check that fails
    records why, and logs it for the admins' log."""
    try:
        findings, entries, skipped = _findings(session, settings, check.split)
    except Exception as error:  # an organiser's tool: say what failed, keep the service up
        log.exception("integrity check %s failed", check.id)
        check.error, check.finished_at = f"{type(error).__name__}: {error}", utc_now()
        return
    # Only older checks are deleted here, so two overlapping checks never wait on each other's rows.
    newer_finished = select(IntegrityCheck.id).where(
        IntegrityCheck.split_id == check.split_id,
        IntegrityCheck.id > check.id,
        IntegrityCheck.finished_at.is_not(None),
    )
    if session.scalars(newer_finished).first() is not None:
        session.delete(check)
        return
    session.execute(
        delete(IntegrityCheck).where(IntegrityCheck.split_id == check.split_id, IntegrityCheck.id < check.id)
    )
    for finding in findings:
        session.add(
            IntegrityFlag(
                check_id=check.id,
                kind=finding.kind,
                submission_id=finding.submission_id,
                other_submission_id=finding.other_submission_id,
                summary=finding.summary,
                evidence=finding.evidence,
            )
        )
    check.entries, check.skipped, check.finished_at = entries, skipped, utc_now()


def _findings(
    session: Session, settings: Settings, split: Split
) -> tuple[list[Finding], int, list[dict[str, Any]]]:
    """Return the findings on a split's non-baseline submissions, how many were read, and the skipped ones."""
    from scorer.submission import SubmissionError

    tokens = list(split_tokens(split))
    futures = human_futures(
        Path(split.directory), split.content_hash, settings.cache_dir, settings.cache_store
    )
    human = _aligned(futures, tokens)
    submissions = session.scalars(
        select(Submission)
        .where(Submission.split_id == split.id, Submission.is_baseline.is_(False))
        .order_by(Submission.created_at, Submission.id)
    ).all()
    findings: list[Finding] = []
    entries: dict[str, list[Entry]] = defaultdict(list)
    skipped = []
    for submission in submissions:
        try:
            seeds = submission_trajectories(
                settings.submission_store, submission.stored_name, submission.sha256, submission.filename
            )
        except (OSError, SubmissionError) as error:
            skipped.append({"submission": submission.id, "reason": type(error).__name__})
            continue
        aligned = [_aligned(predictions, tokens) for predictions in seeds]
        leak = leaked_log(submission.id, aligned, human, tokens)
        if leak is not None:
            findings.append(leak)
        entries[submission.team.name].append(
            Entry(submission.id, submission.team.name, submission.sha256, tuple(aligned))
        )
    every = sorted((e for team in entries.values() for e in team), key=lambda e: e.submission_id)
    findings += near_duplicates(every, tokens)
    findings += [f for team in entries.values() if (f := probing(team, tokens)) is not None]
    return findings, len(every), skipped


def integrity_report(session: Session) -> dict[str, Any]:
    """Return each split's latest check and its flags, each with the flagged submission's state."""
    checks = session.scalars(select(IntegrityCheck).order_by(IntegrityCheck.id.desc())).all()
    flags = session.scalars(select(IntegrityFlag).order_by(IntegrityFlag.id)).all()
    by_check: dict[int, list[IntegrityFlag]] = defaultdict(list)
    for flag in flags:
        by_check[flag.check_id].append(flag)
    return {
        "checks": [
            {
                "id": check.id,
                "split": check.split.name,
                "started_at": check.started_at,
                "finished_at": check.finished_at,
                "entries": check.entries,
                "skipped": check.skipped,
                "error": check.error,
                "flags": [_flag_view(flag) for flag in by_check[check.id]],
            }
            for check in checks
        ]
    }


def _flag_view(flag: IntegrityFlag) -> dict[str, Any]:
    submission = flag.submission
    return {
        "id": flag.id,
        "kind": flag.kind,
        "submission_id": flag.submission_id,
        "other_submission_id": flag.other_submission_id,
        "team": submission.team.name,
        "method": submission.method,
        "admin_hidden": submission.admin_hidden,
        "disqualified": submission.disqualified,
        "summary": flag.summary,
        "evidence": flag.evidence,
    }
