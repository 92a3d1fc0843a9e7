"""What a submission may be compared with, token by token, and the other entry's rows for that comparison.

A team compares a submission of its own with any of: its other scored submissions on the same split, the
entries published on that split (`published_submission`: scored, shown on the board, their phase closed) and
the split's baselines. Another team's entry that is not published is neither offered nor read. The other
entry's rows are cut to the tokens the caller may see of the compared submission (its phase decides), so that
a comparison never reveals a private token's result before its phase closes, a baseline's included.
"""

from __future__ import annotations

from typing import Literal

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.models import Phase, Status, Submission, utc_now
from server.schemas import ComparableOut, SubmissionOut, TokenRow
from server.services.errors import NotFound
from server.services.presenters import submission_views, token_result_views

MAX_LISTED = 200  # the newest of each kind; more would not fit a choice list anyway

Kind = Literal["yours", "published", "baseline"]


def _candidates(session: Session, submission: Submission, owner: bool) -> list[tuple[Kind, Submission]]:
    """Return every entry `submission` may be compared with, with its kind: for its `owner` (its team or an
    organiser), its team's other entries, then for everyone the published entries and the baselines."""
    scored = (
        select(Submission)
        .where(
            Submission.split_id == submission.split_id,
            Submission.status == Status.scored,
            Submission.id != submission.id,
        )
        .order_by(Submission.id.desc())
        .limit(MAX_LISTED)
    )
    entries = scored.where(Submission.is_baseline.is_(False))
    own = session.scalars(entries.where(Submission.team_id == submission.team_id)).all() if owner else []
    # As `published_submission` decides, in the query: shown on the board, its phase closed.
    published = entries.join(Phase, Submission.phase_id == Phase.id).where(
        Submission.hidden.is_(False),
        Submission.admin_hidden.is_(False),
        Submission.disqualified.is_(False),
        Phase.closes_at.is_not(None),
        Phase.closes_at <= utc_now(),
    )
    if owner:
        published = published.where(Submission.team_id != submission.team_id)
    kinds: list[tuple[Kind, Submission]] = [("yours", entry) for entry in own]
    kinds += [("published", entry) for entry in session.scalars(published).all()]
    kinds += [
        ("baseline", entry) for entry in session.scalars(scored.where(Submission.is_baseline.is_(True)))
    ]
    return kinds


def comparable_entries(session: Session, submission: Submission, owner: bool) -> list[ComparableOut]:
    """Return what `submission` may be compared with (`_candidates`), each kind newest first, with their
    results as the board shows them."""
    candidates = _candidates(session, submission, owner)
    views = submission_views(session, [other for _, other in candidates], SubmissionOut)
    return [
        ComparableOut(**view.model_dump(), kind=kind)
        for (kind, _), view in zip(candidates, views, strict=True)
    ]


def comparison_rows(
    session: Session, submission: Submission, other_id: int, version: str, owner: bool, admin: bool
) -> list[TokenRow]:
    """Return the per-token rows of entry `other_id` on the tokens the caller may see of `submission`;
    NotFound unless `other_id` is one `submission` may be compared with (`_candidates`)."""
    candidates = _candidates(session, submission, owner)
    other = next((entry for _, entry in candidates if entry.id == other_id), None)
    if other is None:
        raise NotFound(
            f"submission {other_id} cannot be compared with {submission.id}: choose another of the team's, "
            "a published entry or a baseline of the same split"
        )
    return token_result_views(session, other, version, only_failed=False, admin=admin, seen_as=submission)
