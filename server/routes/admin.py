"""Admin routes (admin token): teams, tokens, quotas, moderation, re-runs, rescore-all, export, audit log.

Every state change is written to the audit log in the same transaction as the change itself.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Annotated, Literal
from urllib.parse import quote

from fastapi import APIRouter, BackgroundTasks, Query, Request
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from sqlalchemy.orm import Session

from scorer.versions import DEFAULT_VERSION, VersionName
from server.auth import AdminDep, SessionDep
from server.models import Approval, Status, Submission
from server.params import PNG_RESPONSE, Offset, OptionalRowId, PictureLayout, RowId, SceneToken, SeedIndex
from server.schemas import (
    AdminSubmissionOut,
    AuditOut,
    ComparableOut,
    DisqualifyIn,
    HideIn,
    IntegrityCheckIn,
    IntegrityReport,
    PhaseIn,
    PhaseOut,
    QuotaIn,
    RescoreIn,
    RescoreReport,
    RescoreStarted,
    SplitAdded,
    SplitIn,
    StageGroupsOut,
    TeamIn,
    TeamOut,
    TokenCreated,
    TokenIn,
    TokenOut,
    TokenRow,
)
from server.services import admin as actions
from server.services.comparisons import comparable_entries, comparison_rows
from server.services.integrity import integrity_report, run_check, start_check
from server.services.leaderboard import leaderboard_view
from server.services.pictures import scene_picture
from server.services.presenters import phase_view, stage_group_views, submission_views, token_result_views
from server.services.splits import list_splits, resolve_phase, split_by_name
from server.services.submissions import get_submission, list_submissions
from server.services.teams import get_team, list_teams

log = logging.getLogger(__name__)
router = APIRouter(prefix="/admin", tags=["admin"])


def _enqueue(request: Request, submission_ids: Iterable[int]) -> None:
    for submission_id in submission_ids:
        try:
            request.app.state.enqueue(submission_id)
        except Exception:  # stays queued in SQL; the reaper re-sends it
            log.exception("could not enqueue submission %s", submission_id)


@router.get("/teams")
def teams(session: SessionDep, _admin: AdminDep) -> list[TeamOut]:
    """Every team, pending ones first."""
    return [TeamOut.model_validate(team) for team in list_teams(session)]


@router.post("/teams", status_code=201)
def add_team(session: SessionDep, admin: AdminDep, team_in: TeamIn) -> TeamOut:
    """Create an approved team."""
    team = actions.add_team(
        session, admin, team_in.name, team_in.members, team_in.affiliation, Approval.approved
    )
    session.commit()
    return TeamOut.model_validate(team)


@router.post("/teams/{team_id}/approve")
def approve(session: SessionDep, admin: AdminDep, team_id: RowId) -> TeamOut:
    """Approve a team: its tokens may now submit."""
    team = actions.decide_team(session, admin, team_id, Approval.approved)
    session.commit()
    return TeamOut.model_validate(team)


@router.post("/teams/{team_id}/reject")
def reject(session: SessionDep, admin: AdminDep, team_id: RowId) -> TeamOut:
    """Reject a team: its tokens may no longer submit."""
    team = actions.decide_team(session, admin, team_id, Approval.rejected)
    session.commit()
    return TeamOut.model_validate(team)


@router.get("/teams/{team_id}/tokens")
def team_tokens(session: SessionDep, _admin: AdminDep, team_id: RowId) -> list[TokenOut]:
    """A team's tokens (never their secrets)."""
    return [TokenOut.model_validate(token) for token in get_team(session, team_id).tokens]


@router.post("/teams/{team_id}/tokens", status_code=201)
def new_team_token(session: SessionDep, admin: AdminDep, team_id: RowId, token_in: TokenIn) -> TokenCreated:
    """Issue a team token; the secret is in this answer only."""
    team = get_team(session, team_id)
    token, secret = actions.issue_token(session, admin, team, token_in.name, token_in.expires_at)
    session.commit()
    return TokenCreated(**TokenOut.model_validate(token).model_dump(), token=secret)


@router.post("/tokens", status_code=201)
def new_admin_token(session: SessionDep, admin: AdminDep, token_in: TokenIn) -> TokenCreated:
    """Issue another admin token."""
    token, secret = actions.issue_token(session, admin, None, token_in.name, token_in.expires_at)
    session.commit()
    return TokenCreated(**TokenOut.model_validate(token).model_dump(), token=secret)


@router.delete("/tokens/{token_id}")
def revoke(session: SessionDep, admin: AdminDep, token_id: RowId) -> TokenOut:
    """Revoke a token (team or admin)."""
    token = actions.withdraw_token(session, admin, token_id)
    session.commit()
    return TokenOut.model_validate(token)


@router.put("/teams/{team_id}/quotas")
def quotas(session: SessionDep, admin: AdminDep, team_id: RowId, quota_in: QuotaIn) -> QuotaIn:
    """Override a team's quotas in a phase (null keeps the phase default)."""
    phase = resolve_phase(session, quota_in.phase)
    actions.override_quotas(
        session, admin, team_id, phase, quota_in.per_day, quota_in.total, quota_in.in_flight
    )
    session.commit()
    return quota_in


@router.post("/splits", status_code=201)
def add_split(request: Request, session: SessionDep, admin: AdminDep, split_in: SplitIn) -> SplitAdded:
    """Register a split directory (on the server's disk) and queue its two baselines."""
    store = request.app.state.settings.submission_store
    split, baselines = actions.add_split(
        session,
        admin,
        split_in.name,
        split_in.directory,
        split_in.public_tokens,
        split_in.scenes_public,
        store if split_in.baselines else None,
    )
    session.commit()
    _enqueue(request, [submission.id for submission in baselines])
    return SplitAdded(
        name=split.name,
        token_count=split.token_count,
        content_hash=split.content_hash,
        baseline_submissions=[submission.id for submission in baselines],
    )


@router.post("/phases", status_code=201)
def add_phase(session: SessionDep, admin: AdminDep, phase_in: PhaseIn) -> PhaseOut:
    """Create a phase on a registered split."""
    phase = actions.add_phase(
        session,
        admin,
        phase_in.name,
        phase_in.split,
        phase_in.opens_at,
        phase_in.closes_at,
        phase_in.per_day,
        phase_in.total,
        phase_in.in_flight,
    )
    session.commit()
    return phase_view(phase)


@router.get("/submissions")
def submissions(
    session: SessionDep,
    _admin: AdminDep,
    team_id: OptionalRowId = None,
    status: Status | None = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 200,
    offset: Offset = 0,
) -> list[AdminSubmissionOut]:
    """Every submission, newest first, with the admin-only fields."""
    return submission_views(
        session, list_submissions(session, team_id, status, limit, offset), AdminSubmissionOut
    )


def _one(session: Session, submission: Submission) -> AdminSubmissionOut:
    return submission_views(session, [submission], AdminSubmissionOut)[0]


@router.post("/submissions/{submission_id}/rerun")
def rerun(request: Request, session: SessionDep, admin: AdminDep, submission_id: RowId) -> AdminSubmissionOut:
    """Score a submission again (a new run); its current results stay shown until the new run is scored."""
    submission = actions.rerun_submission(session, admin, submission_id)
    session.commit()
    _enqueue(request, [submission.id])
    return _one(session, submission)


@router.post("/submissions/{submission_id}/cancel")
def cancel(session: SessionDep, admin: AdminDep, submission_id: RowId) -> AdminSubmissionOut:
    """Cancel a queued or running submission (refunded)."""
    submission = actions.cancel_submission(session, admin, submission_id)
    session.commit()
    return _one(session, submission)


@router.post("/submissions/{submission_id}/hide")
def hide(session: SessionDep, admin: AdminDep, submission_id: RowId, hide_in: HideIn) -> AdminSubmissionOut:
    """Hide a submission from the leaderboard, or show it again."""
    submission = actions.hide_submission(session, admin, submission_id, hide_in.hidden)
    session.commit()
    return _one(session, submission)


@router.post("/submissions/{submission_id}/disqualify")
def disqualify(
    session: SessionDep, admin: AdminDep, submission_id: RowId, body: DisqualifyIn
) -> AdminSubmissionOut:
    """Disqualify a submission with a reason, or lift the disqualification."""
    submission = actions.disqualify_submission(session, admin, submission_id, body.disqualified, body.reason)
    session.commit()
    return _one(session, submission)


@router.post("/rescore", status_code=202)
def rescore(request: Request, session: SessionDep, admin: AdminDep, body: RescoreIn) -> RescoreStarted:
    """Re-run every scored entry of a phase; the report compares the ranking under `version` after with the one
    under `compare_with` (by default `version`) before."""
    view = leaderboard_view(session, body.version, body.subset, "score", body.phase, admin=True)
    rescore_run, queued = actions.start_rescore(
        session,
        admin,
        resolve_phase(session, view["phase"]),
        view["version"],
        view["subset"],
        body.compare_with,
    )
    session.commit()
    _enqueue(request, [submission.id for submission in queued])
    report = str(request.url_for("rescore_report_route", rescore_id=rescore_run.id))
    return RescoreStarted(id=rescore_run.id, queued=len(queued), report=report)


@router.post("/integrity/checks", status_code=202)
def integrity_check(
    request: Request,
    session: SessionDep,
    admin: AdminDep,
    body: IntegrityCheckIn,
    background: BackgroundTasks,
) -> IntegrityReport:
    """Check a split's entries (or every split's) for a leaked log, copies between teams and probing. The check
    runs once this answer is sent; GET /admin/integrity shows it and its flags when it is done."""
    splits = [split_by_name(session, body.split)] if body.split is not None else list_splits(session)
    checks = [start_check(session, admin, split) for split in splits]
    session.commit()
    for check in checks:
        background.add_task(
            run_check, request.app.state.session_factory, request.app.state.settings, check.id
        )
    report = integrity_report(session)
    started = {check.id for check in checks}
    return IntegrityReport.model_validate(
        {"checks": [check for check in report["checks"] if check["id"] in started]}
    )


@router.get("/integrity")
def integrity(session: SessionDep, _admin: AdminDep) -> IntegrityReport:
    """Each split's latest integrity check and its flags, with their evidence (never shown to teams)."""
    return IntegrityReport.model_validate(integrity_report(session))


@router.get("/rescores/{rescore_id}", name="rescore_report_route")
def rescore_report(session: SessionDep, _admin: AdminDep, rescore_id: RowId) -> RescoreReport:
    """Rank-change report of a rescore: moved entries and Kendall's tau; `complete` once every run finished."""
    return RescoreReport.model_validate(actions.rescore_report(session, rescore_id))


@router.get("/export", response_model=None)
def export(
    session: SessionDep,
    _admin: AdminDep,
    version: VersionName | None = None,
    subset: str | None = None,
    phase: str | None = None,
    format: Literal["csv", "json"] = "csv",
) -> PlainTextResponse | JSONResponse:
    """Every scored submission of a phase (moderation flags included) as CSV or JSON (by default under the
    phase's version)."""
    view = leaderboard_view(session, version, subset, "score", phase, admin=True)
    version = VersionName(view["version"])
    rows = actions.export_rows(session, resolve_phase(session, view["phase"]), version, view["subset"])
    name = f"navsim-lb-{view['phase']}-{version}-{view['subset']}"
    if format == "json":
        body = {"version": version, "phase": view["phase"], "subset": view["subset"], "rows": rows}
        return JSONResponse(body, headers=_attachment(f"{name}.json"))
    return PlainTextResponse(
        actions.rows_to_csv(rows), media_type="text/csv", headers=_attachment(f"{name}.csv")
    )


def _attachment(filename: str) -> dict[str, str]:
    """Return a Content-Disposition for a download: an ASCII name, and the real one as RFC 6266's filename*."""
    fallback = "".join(c if c.isascii() and (c.isalnum() or c in "-_.") else "_" for c in filename)
    return {"Content-Disposition": f"attachment; filename=\"{fallback}\"; filename*=UTF-8''{quote(filename)}"}


@router.get("/audit")
def audit(
    session: SessionDep,
    _admin: AdminDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 200,
    offset: Offset = 0,
) -> list[AuditOut]:
    """The audit log, newest first."""
    return [AuditOut.model_validate(entry) for entry in actions.audit_log(session, limit, offset)]


@router.get("/submissions/{submission_id}")
def submission(session: SessionDep, _admin: AdminDep, submission_id: RowId) -> AdminSubmissionOut:
    """One submission with the admin-only fields."""
    return _one(session, get_submission(session, submission_id))


@router.get(
    "/submissions/{submission_id}/scenes/{token}.png", response_class=Response, responses=PNG_RESPONSE
)
def scene_picture_route(
    request: Request,
    session: SessionDep,
    _admin: AdminDep,
    submission_id: RowId,
    token: SceneToken,
    version: VersionName = DEFAULT_VERSION,
    seed: SeedIndex = 0,
    layout: PictureLayout = "wide",
) -> Response:
    """The picture that explains a submission's score on any token of any split."""
    submission = get_submission(session, submission_id)
    settings = request.app.state.settings
    return Response(
        scene_picture(submission, token, version, seed, layout, admin=True, settings=settings),
        media_type="image/png",
    )


@router.get("/submissions/{submission_id}/groups")
def stage_groups(
    session: SessionDep,
    _admin: AdminDep,
    submission_id: RowId,
    version: VersionName = VersionName.V2_2_TWO_STAGE,
) -> StageGroupsOut:
    """A two-stage submission's groups per seed."""
    return stage_group_views(session, get_submission(session, submission_id), version)


@router.get("/submissions/{submission_id}/comparable")
def comparable(session: SessionDep, _admin: AdminDep, submission_id: RowId) -> list[ComparableOut]:
    """What a submission may be compared with: its team's other scored submissions on the split, the
    entries published on it and its baselines."""
    return comparable_entries(session, get_submission(session, submission_id), owner=True)


@router.get("/submissions/{submission_id}/comparable/{other_id}/tokens")
def comparable_token_rows(
    session: SessionDep,
    _admin: AdminDep,
    submission_id: RowId,
    other_id: RowId,
    version: VersionName = DEFAULT_VERSION,
) -> list[TokenRow]:
    """Per-token results, on every token, of an entry the submission may be compared with."""
    submission = get_submission(session, submission_id)
    return comparison_rows(session, submission, other_id, version, owner=True, admin=True)


@router.get("/submissions/{submission_id}/tokens")
def token_rows(
    session: SessionDep,
    _admin: AdminDep,
    submission_id: RowId,
    version: VersionName = DEFAULT_VERSION,
    only_failed: bool = False,
) -> list[TokenRow]:
    """Per-token results of a submission's current run on every token."""
    return token_result_views(
        session, get_submission(session, submission_id), version, only_failed, admin=True
    )
