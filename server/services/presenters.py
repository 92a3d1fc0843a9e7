"""Read-side presenters: stored rows shaped into the response models the team, public and admin routes answer."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from typing import Any, TypeVar

from sqlalchemy import select
from sqlalchemy.orm import Session, undefer

from scorer.ec_undefined import ec_undefined_reason
from scorer.versions import VersionName, get_version
from server.models import Phase, Result, Submission, Summary, TokenResultRow
from server.runs import run_versions
from server.schemas import (
    AdminSubmissionOut,
    PhaseOut,
    QuotaOut,
    SeedResult,
    SplitOut,
    StageGroupOut,
    StageGroupsOut,
    StageSeedOut,
    SubmissionOut,
    SubsetResult,
    TokenRow,
)
from server.services.errors import NotFound
from server.services.leaderboard import (
    default_subset,
    shown_entries,
    stage_figures,
    subscore_columns,
    summary_figures,
)
from server.services.quota import quota_usage
from server.services.splits import (
    ALL_SUBSET,
    is_open,
    list_phases,
    list_splits,
    subset_tokens,
    visible_subsets,
)
from server.services.submissions import final_refusal


def _subset_result(summary: Summary, results: list[Result]) -> SubsetResult:
    return SubsetResult(
        **summary_figures(summary, subscore_columns(summary.metric_version)),
        **stage_figures(summary.two_stage),
        per_seed=[
            SeedResult(
                seed=result.seed,
                score=result.score,
                tokens=result.tokens,
                failed_tokens=result.failed,
                engine_version=result.engine_version,
                split_hash=result.split_hash,
                workers=result.workers,
                duration_s=result.duration_s,
            )
            for result in sorted(results, key=lambda r: r.seed)
        ],
    )


SubmissionView = TypeVar("SubmissionView", SubmissionOut, AdminSubmissionOut)


def submission_views(
    session: Session, submissions: Sequence[Submission], view: type[SubmissionView]
) -> list[SubmissionView]:
    """Return submissions as `view` (the team's or the admin's) with their per-version results on the subsets
    that view may see."""
    admin = view is AdminSubmissionOut
    ids = [submission.id for submission in submissions]
    summaries = session.scalars(select(Summary).where(Summary.submission_id.in_(ids))).all() if ids else []
    results: dict[tuple[int, str, str], list[Result]] = defaultdict(list)
    for result in session.scalars(select(Result).where(Result.submission_id.in_(ids))).all() if ids else []:
        results[result.submission_id, result.metric_version, result.subset].append(result)
    by_submission: dict[int, list[Summary]] = defaultdict(list)
    for summary in summaries:
        by_submission[summary.submission_id].append(summary)
    shown = _shown_versions(session, submissions)
    views = []
    for submission in submissions:
        visible = set(visible_subsets(submission.split, submission.phase, admin))
        nested: dict[str, dict[str, SubsetResult]] = {
            version: {} for version in run_versions(submission.split)
        }
        for summary in by_submission[submission.id]:
            if summary.subset in visible:
                key = (submission.id, summary.metric_version, summary.subset)
                nested.setdefault(summary.metric_version, {})[summary.subset] = _subset_result(
                    summary, results[key]
                )
        fields = _submission_fields(submission, admin)
        scored = {v: r for v, r in nested.items() if r}
        views.append(view(**fields, on_leaderboard=shown[submission.id], results=scored))
    return views


def _shown_versions(session: Session, submissions: Sequence[Submission]) -> dict[int, list[str]]:
    """Return per submission the metric versions whose leaderboard of its phase shows it (the board's choice)."""
    teams: dict[Phase, set[int]] = defaultdict(set)
    for submission in submissions:
        if submission.phase is not None:
            teams[submission.phase].add(submission.team_id)
    shown: dict[int, list[str]] = defaultdict(list)
    for phase, team_ids in teams.items():
        subset = default_subset(phase)
        for version in run_versions(phase.split):
            for submission_id in shown_entries(session, phase, version, subset, team_ids):
                shown[submission_id].append(version)
    return shown


def _submission_fields(submission: Submission, admin: bool) -> dict[str, Any]:
    fields = {
        "id": submission.id,
        "team": submission.team.name,
        "phase": submission.phase.name if submission.phase else None,
        "split": submission.split.name,
        "baseline": submission.is_baseline,
        "status": submission.status,
        "progress": submission.progress,
        "error": submission.error,
        "method": submission.method,
        "authors": submission.authors,
        "institution": submission.institution,
        "country": submission.country,
        "tech_report_url": submission.tech_report_url,
        "code_url": submission.code_url,
        "seed_count": submission.seed_count,
        "token_count": submission.token_count,
        "filename": submission.filename,
        "sha256": submission.sha256,
        "size_bytes": submission.size_bytes,
        "hidden": submission.hidden,
        "admin_hidden": submission.admin_hidden,
        "disqualified": submission.disqualified,
        "disqualified_reason": submission.disqualified_reason,
        "selected": submission.selected,
        "final_refusal": final_refusal(submission),
        "submitted_at": submission.created_at,
        "started_at": submission.started_at,
        "finished_at": submission.finished_at,
    }
    if admin:
        fields.update(
            team_id=submission.team_id,
            queued_at=submission.queued_at,
            run=submission.run,
            attempts=submission.attempts,
            worker=submission.worker,
            charged=submission.charged,
            failure_kind=submission.failure_kind,
            error_detail=submission.error_detail,
        )
    return fields


def phase_view(phase: Phase) -> PhaseOut:
    """Return a phase with whether it is open now."""
    return PhaseOut(
        name=phase.name,
        split=phase.split.name,
        opens_at=phase.opens_at,
        closes_at=phase.closes_at,
        versions=list(run_versions(phase.split)),
        open=is_open(phase),
        per_day=phase.per_day,
        total=phase.total,
        in_flight=phase.in_flight,
    )


def token_result_views(
    session: Session,
    submission: Submission,
    version: str,
    only_failed: bool,
    admin: bool,
    seen_as: Submission | None = None,
) -> list[TokenRow]:
    """Return the per-token rows of a submission's current run on the tokens the caller may see: of that
    submission, or of `seen_as` when the rows are read beside it (a comparison: its phase decides)."""
    subsets = subset_tokens(submission.split)
    allowed = {
        token
        for name in visible_subsets(submission.split, (seen_as or submission).phase, admin=admin)
        for token in subsets[name]
    }
    query = select(TokenResultRow).where(
        TokenResultRow.submission_id == submission.id,
        TokenResultRow.run == submission.run,
        TokenResultRow.metric_version == version,
    )
    if only_failed:
        query = query.where(TokenResultRow.valid.is_(False))
    rows = session.scalars(query.order_by(TokenResultRow.seed, TokenResultRow.token)).all()
    return [
        TokenRow(
            token=row.token,
            metric_version=row.metric_version,
            seed=row.seed,
            valid=row.valid,
            error=row.error,
            metrics={column: getattr(row, column) for column in get_version(version).result_columns},
            detail=_detail(row.detail or {}, admin),
            ec_undefined=_ec_undefined(row),
        )
        for row in rows
        if row.token in allowed
    ]


def _ec_undefined(row: TokenResultRow) -> str | None:
    """Return why a scored v2.2 row has no two-frame extended comfort, or None (defined, or not in the version)."""
    if not row.valid or row.two_frame_extended_comfort is not None:
        return None
    if "two_frame_extended_comfort" not in get_version(row.metric_version).result_columns:
        return None
    return ec_undefined_reason(row.token, row.detail or {})


def _detail(detail: dict[str, Any], admin: bool) -> dict[str, Any]:
    """Return a row's detail as the caller may read it: a team sees which columns the human filter set to 1
    (the logged human scores 0 there too) and its own values there before, not the rest of the human's
    scores on a hidden log (nor, to keep a navtest-size answer small, its values the filter left alone)."""
    human_filter = detail.get("human_filter")
    if admin or not human_filter:
        return detail
    overridden = human_filter["overridden"]
    before = human_filter.get("agent_before", {})
    seen = {k: v for k, v in human_filter.items() if k not in ("human", "agent_before")}
    if overridden:
        seen["agent_before"] = {column: before[column] for column in overridden}
    return detail | {"human_filter": seen}


def split_views(session: Session) -> list[SplitOut]:
    """Return the registered splits with their token counts, content hashes, subsets and phases."""
    phases = list_phases(session)
    return [
        SplitOut(
            name=split.name,
            token_count=split.token_count,
            content_hash=split.content_hash,
            scenes_public=split.scenes_public,
            subsets={subset.name: len(subset.tokens) for subset in split.subsets}
            | {ALL_SUBSET: split.token_count},
            phases=[phase_view(phase) for phase in phases if phase.split_id == split.id],
        )
        for split in list_splits(session)
    ]


def quota_views(session: Session, team_id: int) -> list[QuotaOut]:
    """Return a team's usage of every quota in every open phase."""
    return [
        QuotaOut(
            phase=phase.name, quota=usage.name, limit=usage.limit, used=usage.used, resets_at=usage.resets_at
        )
        for phase in list_phases(session)
        if is_open(phase)
        for usage in quota_usage(session, team_id, phase)
    ]


def stage_group_views(session: Session, submission: Submission, version: str) -> StageGroupsOut:
    """Return a two-stage submission's groups per seed under `version` (a two-stage version); NotFound for a
    one-stage one, or one not scored yet."""
    if not get_version(version).two_stage:
        raise NotFound(f"{version} is a one-stage version: its results have no groups (see /tokens)")
    query = select(Result).where(
        Result.submission_id == submission.id, Result.metric_version == version, Result.two_stage.is_not(None)
    )
    results = sorted(session.scalars(query.options(undefer(Result.two_stage))).all(), key=lambda r: r.seed)
    if not results:
        raise NotFound(f"submission {submission.id} has no two-stage results under {version}")
    return StageGroupsOut(
        version=VersionName(version),
        seeds=[_stage_seed(result.seed, result.score, result.two_stage or {}) for result in results],
    )


def _stage_seed(seed: int, score: float | None, two_stage: dict[str, Any]) -> StageSeedOut:
    """Return one seed's two-stage part (`Result.two_stage`) as the API shows it."""
    return StageSeedOut(
        seed=seed,
        score=score,
        stage_one=two_stage["stage_one"],
        stage_two=two_stage["stage_two"],
        official=two_stage["official"],
        notes=two_stage["notes"],
        note_count=two_stage["note_count"],
        groups=[
            StageGroupOut(
                original=group["original"],
                previous=group["previous"],
                **{part: columns["score"] for part, columns in group["parts"].items()},
                score=group["combined"]["score"],
                weights=group["weights"],
                detail=group["detail"],
            )
            for group in two_stage["groups"]
        ],
    )
