"""Submissions: the atomic create path (lock, idempotency, duplicates, quota), baselines, team edits."""

from __future__ import annotations

import io
from collections.abc import Sequence
from datetime import datetime
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from server.models import Phase, Split, Status, Submission, Team, utc_now
from server.object_store import ObjectStore
from server.services.errors import Conflict, Forbidden, NotFound
from server.services.quota import check_quota, lock_team
from server.services.splits import has_closed, is_open
from server.services.teams import baseline_team
from server.services.validation import ValidUpload
from server.storage import store_file, store_trajectories, stored_name

# Statuses after which the same file may be uploaded again (it was never scored to the end).
RETRYABLE_STATUSES = (Status.failed, Status.cancelled)
BASELINES = (("constant-velocity", "Constant Velocity"), ("human", "Human"))
EDITABLE_FIELDS = ("method", "authors", "institution", "country", "tech_report_url", "code_url", "hidden")


def _store(store: ObjectStore, upload: ValidUpload) -> str:
    """Store the uploaded file and the trajectories its check parsed; return the file's stored name. Both are
    stored before the row that names them is added (StoreUnavailable leaves no row)."""
    if upload.staged is not None:  # streamed to the store as it was checked
        name = stored_name(upload.sha256)
        upload.staged.commit(name)
    else:
        assert upload.data is not None
        name = store_file(store, upload.sha256, io.BytesIO(upload.data))
    if upload.trajectories:
        store_trajectories(store, name, upload.sha256, upload.trajectories)
    return name


def _new_submission(
    team: Team, split: Split, phase: Phase | None, upload: ValidUpload, stored: str
) -> Submission:
    return Submission(
        team=team,
        split=split,
        phase=phase,
        sha256=upload.sha256,
        filename=upload.filename,
        stored_name=stored,
        size_bytes=upload.size_bytes,
        seed_count=upload.seed_count,
        token_count=upload.token_count,
        **upload.metadata,
    )


def create_submission(
    session: Session,
    team: Team,
    phase: Phase,
    upload: ValidUpload,
    store: ObjectStore,
    idempotency_key: str | None = None,
    now: datetime | None = None,
) -> tuple[Submission, bool]:
    """Insert a queued submission and store its file; return it and whether it replays an earlier request.

    Runs under the team lock, so idempotency, duplicate and quota checks see every earlier upload of
    the team. The caller commits, then enqueues unless it was a replay.
    """
    now = now or utc_now()
    if not is_open(phase, now):
        raise Forbidden(
            f"phase {phase.name!r} is not open for submissions (opens {phase.opens_at.isoformat()}"
            + (f", closes {phase.closes_at.isoformat()})" if phase.closes_at else ")")
        )
    lock_team(session, team.id, now)
    if idempotency_key:
        earlier = session.scalar(
            select(Submission).where(
                Submission.team_id == team.id, Submission.idempotency_key == idempotency_key
            )
        )
        if earlier is not None:
            if earlier.sha256 != upload.sha256 or earlier.phase_id != phase.id:
                raise Conflict(
                    f"Idempotency-Key {idempotency_key!r} was used for submission {earlier.id} with another file",
                    submission_id=earlier.id,
                )
            return earlier, True
    duplicate = session.scalar(
        select(Submission).where(
            Submission.team_id == team.id,
            Submission.phase_id == phase.id,
            Submission.sha256 == upload.sha256,
            Submission.status.not_in(RETRYABLE_STATUSES),
        )
    )
    if duplicate is not None:
        raise Conflict(
            f"this file (sha256 {upload.sha256[:12]}…) is already submission {duplicate.id} ({duplicate.status}); "
            "it is not scored twice",
            submission_id=duplicate.id,
        )
    check_quota(session, team.id, phase, now)
    submission = _new_submission(team, phase.split, phase, upload, _store(store, upload))
    submission.idempotency_key = idempotency_key or None
    submission.created_at = submission.queued_at = now
    session.add(submission)
    session.flush()
    return submission, False


def add_baselines(session: Session, split: Split, store: ObjectStore) -> list[Submission]:
    """Create the queued constant-velocity and human baseline submissions of a split (the caller enqueues them),
    in the split's form (one-stage or two-stage)."""
    from scorer.baselines import baseline_submission, two_stage_baseline_submission
    from scorer.submission import dump_submission_json, dump_two_stage_submission_json
    from server.services.splits import split_tokens, upload_stages
    from server.services.validation import validate_upload
    from server.split_store import local_scenes

    team = baseline_team(session)
    tokens = split_tokens(split)
    stages = upload_stages(split)
    created = []
    for kind, method in BASELINES:
        directory = local_scenes(split.directory, split.content_hash, tokens)
        if stages is None:
            data = dump_submission_json(baseline_submission(directory, kind, method))
        else:
            data = dump_two_stage_submission_json(two_stage_baseline_submission(directory, kind, method))
        upload = validate_upload(data, f"{kind}.json", tokens, {"method": method}, stages)
        submission = _new_submission(team, split, None, upload, _store(store, upload))
        submission.is_baseline = True
        submission.charged = False
        session.add(submission)
        created.append(submission)
    session.flush()
    return created


def get_submission(session: Session, submission_id: int, team_id: int | None = None) -> Submission:
    """Return a submission; with `team_id`, only one of that team's (others are reported as missing)."""
    submission = session.get(Submission, submission_id)
    if submission is None or (team_id is not None and submission.team_id != team_id):
        raise NotFound(f"submission {submission_id} does not exist")
    return submission


def published_submission(session: Session, submission_id: int, now: datetime | None = None) -> Submission:
    """Return a submission anyone may read: a scored leaderboard entry of a phase that has closed."""
    submission = session.get(Submission, submission_id)
    phase = submission.phase if submission is not None else None
    published = (
        submission is not None
        and phase is not None
        and submission.status == Status.scored
        and not (submission.hidden or submission.admin_hidden or submission.disqualified)
        and has_closed(phase, now)
    )
    if not published:
        raise NotFound(
            f"submission {submission_id} is not published: entries are public once their phase has closed"
        )
    assert submission is not None
    return submission


def list_submissions(
    session: Session, team_id: int | None = None, status: str | None = None, limit: int = 200, offset: int = 0
) -> Sequence[Submission]:
    """Return submissions, newest first, optionally of one team and one status."""
    query = select(Submission).order_by(Submission.id.desc()).limit(limit).offset(offset)
    if team_id is not None:
        query = query.where(Submission.team_id == team_id)
    if status is not None:
        query = query.where(Submission.status == status)
    return session.scalars(query).all()


def final_refusal(submission: Submission) -> str | None:
    """Return why a submission cannot be its team's final entry (the leaderboard would not show it), or None.
    The organisers' sanctions come first, with the reason they gave."""
    if submission.disqualified:
        reason = f": {submission.disqualified_reason}" if submission.disqualified_reason else ""
        return f"submission {submission.id} was disqualified by an organiser{reason}"
    if submission.admin_hidden:
        return f"submission {submission.id} was hidden from the leaderboard by an organiser"
    if submission.hidden:
        return f"submission {submission.id} is hidden by your team; show it first"
    if submission.status in RETRYABLE_STATUSES:
        return f"submission {submission.id} is {submission.status}"
    return None


def edit_submission(session: Session, submission: Submission, changes: dict[str, Any]) -> Submission:
    """Apply a team's edit: metadata, hidden, and `selected` (the team's final entry in the phase); an entry
    the leaderboard would not show cannot become final (Conflict, with the reason)."""
    unknown = set(changes) - {*EDITABLE_FIELDS, "selected"}
    if unknown:
        raise Conflict(f"cannot edit {', '.join(sorted(unknown))}")
    for name in EDITABLE_FIELDS:
        if name in changes and changes[name] is not None:
            setattr(submission, name, changes[name])
    if changes.get("selected") is True:
        refusal = final_refusal(submission)
        if refusal is not None:
            raise Conflict(f"{refusal}, so it cannot be the final entry")
        session.execute(
            update(Submission)
            .where(Submission.team_id == submission.team_id, Submission.phase_id == submission.phase_id)
            .values(selected=False)
        )
        submission.selected = True
    elif changes.get("selected") is False:
        submission.selected = False
    session.flush()
    return submission
