"""A run as the database holds it: which run a write belongs to, what it is scored under, what is written.

Every step of a run names the run it belongs to. A re-run increments `Submission.run`, so a late chunk of an
older run, or of a cancelled or finished submission, is dropped instead of mixing with the new one. Writes
that decide on the run's state take the submission's row lock first: under it, the last chunk to finish
sees every other one finished. Per-token rows are keyed by (submission, metric version, seed, token): a
complete run holds tokens x seeds x versions of them.
"""

from __future__ import annotations

from collections.abc import Collection

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from scorer.versions import LOG_REPLAY_VERSIONS, TWO_STAGE_VERSIONS, VersionName
from server.models import ACTIVE_STATUSES, Split, SplitKind, Submission, TokenResultRow
from server.services.errors import NotFound

# The versions a run is scored under and its phase's board shows, by the kind of its split: log-replay splits
# under the versions whose traffic replays the log, two-stage splits under NAVSIM's two-stage EPDMS.
RUN_VERSIONS: dict[SplitKind, tuple[VersionName, ...]] = {
    SplitKind.log_replay: LOG_REPLAY_VERSIONS,
    SplitKind.two_stage: TWO_STAGE_VERSIONS,
}
# Every version some board shows.
BOARD_VERSIONS = tuple(dict.fromkeys(version for versions in RUN_VERSIONS.values() for version in versions))


def run_versions(split: Split) -> tuple[VersionName, ...]:
    """Return the metric versions a run on `split` is scored under (its kind's)."""
    return RUN_VERSIONS[SplitKind(split.kind)]


def locked_submission(session: Session, submission_id: int) -> Submission:
    """Return the submission with its row locked for the transaction; NotFound when there is none."""
    submission = session.scalar(select(Submission).where(Submission.id == submission_id).with_for_update())
    if submission is None:
        raise NotFound(f"submission {submission_id} does not exist")
    return submission


def is_current(submission: Submission, run: int) -> bool:
    """Whether a write for `run` still belongs: the submission is active and not re-run since."""
    return submission.run == run and submission.status in ACTIVE_STATUSES


def expected_rows(submission: Submission) -> int:
    """Return how many per-token rows a complete run holds: tokens x seeds x metric versions."""
    return submission.token_count * submission.seed_count * len(run_versions(submission.split))


def rows_written(session: Session, submission_id: int, run: int) -> int:
    """Return how many per-token rows of `run` are stored."""
    query = select(func.count()).where(
        TokenResultRow.submission_id == submission_id, TokenResultRow.run == run
    )
    return session.scalar(query) or 0


def completed_tokens(
    session: Session, submission_id: int, run: int, among: Collection[str] | None = None
) -> set[str] | None:
    """Return the tokens of `run` with every version and seed written, of `among` only if given (a chunk's
    tokens: an index finds their rows alone, whatever the size of the run); None when the run is no longer
    wanted."""
    submission = session.get(Submission, submission_id)
    if submission is None or not is_current(submission, run):
        return None
    query = select(TokenResultRow.token).where(
        TokenResultRow.submission_id == submission_id, TokenResultRow.run == run
    )
    if among is not None:
        query = query.where(TokenResultRow.token.in_(among))
    grouped = query.group_by(TokenResultRow.token).having(
        func.count() == submission.seed_count * len(run_versions(submission.split))
    )
    return set(session.scalars(grouped).all())
