"""Public routes: leaderboard, splits and phases, health, team registration, and the caller's own token."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response

from scorer.versions import DEFAULT_VERSION, VersionName
from server.auth import SessionDep, TokenDep
from server.models import Approval, Scope
from server.params import PNG_RESPONSE, PictureLayout, RowId, SceneToken, SeedIndex
from server.schemas import (
    ComparableOut,
    HealthOut,
    LeaderboardOut,
    MeOut,
    PhaseOut,
    SplitOut,
    StageGroupsOut,
    SubmissionOut,
    TeamIn,
    TeamOut,
    TeamRegistered,
    TokenRow,
)
from server.services.comparisons import comparable_entries, comparison_rows
from server.services.health import health_report
from server.services.leaderboard import cached_board
from server.services.pictures import scene_picture
from server.services.presenters import (
    phase_view,
    quota_views,
    split_views,
    stage_group_views,
    submission_views,
    token_result_views,
)
from server.services.splits import list_phases
from server.services.submissions import published_submission
from server.services.teams import create_team
from server.services.tokens import create_token

router = APIRouter()


@router.get("/leaderboard", response_model=LeaderboardOut, tags=["leaderboard"])
async def get_leaderboard(
    request: Request,
    version: VersionName | None = None,
    subset: str | None = None,
    sort: str = "score",
    phase: str | None = None,
) -> Response:
    """Best (or selected) entry per team plus baselines, ranked by the version's score (PDMS or EPDMS) with bootstrap 95% intervals.
    Without a version, the phase's default: the default version on a one-stage split, v2.2-two-stage on a
    two-stage one."""
    cache, sessions = request.app.state.leaderboard_cache, request.app.state.session_factory
    board = cache.get((version, subset, sort, phase))
    if board is None:  # the database is only asked off the event loop
        board = await run_in_threadpool(cached_board, cache, sessions, version, subset, sort, phase)
    return Response(board.body, media_type="application/json")


@router.get("/splits", tags=["splits"])
def splits(session: SessionDep) -> list[SplitOut]:
    """Registered splits with their token counts, content hashes, subsets and phases."""
    return split_views(session)


@router.get("/phases", tags=["splits"])
def phases(session: SessionDep) -> list[PhaseOut]:
    """Every phase with its window and default quotas."""
    return [phase_view(phase) for phase in list_phases(session)]


@router.get("/health", response_model=HealthOut, tags=["health"])
def health(request: Request, session: SessionDep) -> JSONResponse:
    """Database, broker and live workers; 503 when the database does not answer."""
    state = request.app.state
    broker, workers = state.broker_status(state.settings), state.live_workers(state.settings)
    body = health_report(session, state.engine, broker, workers)
    status_code = 200 if body["database"]["ok"] else 503
    return JSONResponse(HealthOut(**body).model_dump(mode="json"), status_code=status_code)


@router.post("/teams", status_code=201, tags=["teams"])
def register_team(session: SessionDep, team_in: TeamIn) -> TeamRegistered:
    """Register a team (pending until an admin approves it); answers its first token, shown once."""
    team = create_team(session, team_in.name, team_in.members, team_in.affiliation, Approval.pending)
    _, secret = create_token(session, Scope.team, team, name="registration")
    session.commit()
    return TeamRegistered(team=TeamOut.model_validate(team), token=secret)


@router.get("/me", tags=["teams"])
def me(session: SessionDep, token: TokenDep) -> MeOut:
    """The caller's token, team and quota usage in every open phase."""
    team = token.team
    quotas = quota_views(session, team.id) if team is not None else []
    return MeOut(
        scope=token.scope,
        team=team.name if team else None,
        approval=team.approval if team else None,
        token_prefix=token.prefix,
        expires_at=token.expires_at,
        quotas=quotas,
    )


@router.get("/published/{submission_id}", tags=["published"])
def published(session: SessionDep, submission_id: RowId) -> SubmissionOut:
    """A leaderboard entry whose phase has closed, as its team sees it: open to everyone."""
    return submission_views(session, [published_submission(session, submission_id)], SubmissionOut)[0]


@router.get("/published/{submission_id}/groups", tags=["published"])
def published_stage_groups(
    session: SessionDep, submission_id: RowId, version: VersionName = VersionName.V2_2_TWO_STAGE
) -> StageGroupsOut:
    """A published two-stage entry's groups per seed."""
    return stage_group_views(session, published_submission(session, submission_id), version)


@router.get("/published/{submission_id}/tokens", tags=["published"])
def published_token_rows(
    session: SessionDep, submission_id: RowId, version: VersionName = DEFAULT_VERSION
) -> list[TokenRow]:
    """Per-token results of a published entry."""
    submission = published_submission(session, submission_id)
    return token_result_views(session, submission, version, only_failed=False, admin=False)


@router.get("/published/{submission_id}/comparable", tags=["published"])
def published_comparable(session: SessionDep, submission_id: RowId) -> list[ComparableOut]:
    """What a published entry may be compared with: the entries published on its split and its baselines."""
    return comparable_entries(session, published_submission(session, submission_id), owner=False)


@router.get("/published/{submission_id}/comparable/{other_id}/tokens", tags=["published"])
def published_comparable_token_rows(
    session: SessionDep, submission_id: RowId, other_id: RowId, version: VersionName = DEFAULT_VERSION
) -> list[TokenRow]:
    """Per-token results of a published entry or baseline beside a published entry."""
    submission = published_submission(session, submission_id)
    return comparison_rows(session, submission, other_id, version, owner=False, admin=False)


@router.get(
    "/published/{submission_id}/scenes/{token}.png",
    response_class=Response,
    responses=PNG_RESPONSE,
    tags=["published"],
)
def published_scene_picture(
    request: Request,
    session: SessionDep,
    submission_id: RowId,
    token: SceneToken,
    version: VersionName = DEFAULT_VERSION,
    seed: SeedIndex = 0,
    layout: PictureLayout = "wide",
) -> Response:
    """The drill-down picture of a published entry on one token (splits whose scenes are public only)."""
    submission = published_submission(session, submission_id)
    settings = request.app.state.settings
    picture = scene_picture(submission, token, version, seed, layout, admin=False, settings=settings)
    return Response(picture, media_type="image/png")
