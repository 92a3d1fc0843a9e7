"""Public routes: leaderboard, splits and phases, health, team registration, and the caller's own token."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fastapi import APIRouter, FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from sqlalchemy import select, text
from sqlalchemy.orm import Session

from scorer.versions import DEFAULT_VERSION, VersionName, get_version
from server.auth import SessionDep, TokenDep
from server.migrate import current_revision
from server.models import Approval, Phase, Scope, Split
from server.routes.params import PNG_RESPONSE, RowId, SceneToken, SeedIndex
from server.routes.views import phase_view, submission_views, token_result_views
from server.schemas import (
    HealthOut,
    LeaderboardOut,
    MeOut,
    PhaseOut,
    QuotaOut,
    SplitOut,
    SubmissionOut,
    TeamIn,
    TeamOut,
    TeamRegistered,
    TokenRow,
)
from server.services.errors import Forbidden, NotFound
from server.services.leaderboard import leaderboard, subscore_columns
from server.services.pictures import scene_picture
from server.services.quota import quota_usage
from server.services.splits import (
    ALL_SUBSET,
    PUBLIC_SUBSET,
    has_closed,
    is_open,
    resolve_phase,
    subset_names,
    visible_subsets,
)
from server.services.submissions import published_submission
from server.services.teams import create_team
from server.services.tokens import create_token
from server.services.workers import workers_from_heartbeats

router = APIRouter()


def leaderboard_view(
    session: Session, version: str, subset: str | None, sort: str, phase_name: str | None, admin: bool = False
) -> dict[str, Any]:
    """Return the leaderboard body for the query (shared by the REST route and the web page)."""
    phase = resolve_phase(session, phase_name)
    columns = subscore_columns(version)
    visible = visible_subsets(phase.split, phase, admin)
    if subset is None:
        subset = PUBLIC_SUBSET if PUBLIC_SUBSET in visible else ALL_SUBSET
    known = subset_names(phase.split)
    if subset not in known:
        raise NotFound(f"split {phase.split.name!r} has no subset {subset!r}; it has {', '.join(known)}")
    if subset not in visible:
        closes = phase.closes_at.isoformat() if phase.closes_at else "an admin closes it"
        raise Forbidden(
            f"subset {subset!r} of phase {phase.name!r} is revealed when the phase closes ({closes})"
        )
    metric_version = get_version(version)
    return {
        "version": version,
        "score_label": metric_version.score_label,
        "official_code": metric_version.official_code,
        "phase": phase.name,
        "split": phase.split.name,
        "subset": subset,
        "subsets": visible,
        "closed": has_closed(phase),
        "sort": sort,
        "columns": list(columns),
        "rows": leaderboard(session, phase, version, subset, sort),
    }


@dataclass(frozen=True)
class Board:
    """A leaderboard body and its JSON encoding, computed once per cache period."""

    view: dict[str, Any]
    body: bytes


def cached_board(app: FastAPI, version: str, subset: str | None, sort: str, phase: str | None) -> Board:
    """Return the public leaderboard for the query, from the app's short-lived cache when it is fresh."""
    key = (version, subset, sort, phase)
    board = app.state.leaderboard_cache.get(key)
    if board is None:
        with app.state.session_factory() as session:
            view = leaderboard_view(session, version, subset, sort, phase)
        board = Board(view, bytes(JSONResponse(view).body))
        app.state.leaderboard_cache.put(key, board)
    return board


@router.get("/leaderboard", response_model=LeaderboardOut, tags=["leaderboard"])
async def get_leaderboard(
    request: Request,
    version: VersionName = DEFAULT_VERSION,
    subset: str | None = None,
    sort: str = "score",
    phase: str | None = None,
) -> Response:
    """Best (or selected) entry per team plus baselines, ranked by PDMS with bootstrap 95% intervals."""
    board = request.app.state.leaderboard_cache.get((version, subset, sort, phase))
    if board is None:  # the database is only asked off the event loop
        board = await run_in_threadpool(cached_board, request.app, version, subset, sort, phase)
    return Response(board.body, media_type="application/json")


@router.get("/splits", tags=["splits"])
def splits(session: SessionDep) -> list[SplitOut]:
    """Registered splits with their token counts, content hashes, subsets and phases."""
    phases = session.scalars(select(Phase).order_by(Phase.opens_at)).all()
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
        for split in session.scalars(select(Split).order_by(Split.name)).all()
    ]


@router.get("/phases", tags=["splits"])
def phases(session: SessionDep) -> list[PhaseOut]:
    """Every phase with its window and default quotas."""
    return [phase_view(phase) for phase in session.scalars(select(Phase).order_by(Phase.opens_at)).all()]


@router.get("/health", response_model=HealthOut, tags=["health"])
def health(request: Request, session: SessionDep) -> JSONResponse:
    """Database, broker and live workers; 503 when the database does not answer."""
    try:
        session.execute(text("SELECT 1"))
        database = {"ok": True, "revision": current_revision(request.app.state.engine), "detail": ""}
    except Exception as error:  # noqa: BLE001 - health reports, it does not fail
        database = {"ok": False, "revision": None, "detail": f"{type(error).__name__}: {error}"}
    settings = request.app.state.settings
    broker, workers = request.app.state.broker_status(settings), request.app.state.live_workers(settings)
    if workers["ok"] is None and database["ok"]:  # no ping on this transport: the workers' own heartbeats
        workers = workers_from_heartbeats(session)
    healthy = database["ok"] and broker["ok"] and workers["ok"] is not False
    body = {
        "status": "ok" if healthy else "degraded",
        "database": database,
        "broker": broker,
        "workers": workers,
    }
    return JSONResponse(HealthOut(**body).model_dump(mode="json"), status_code=200 if database["ok"] else 503)


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
    quotas = []
    if team is not None:
        for phase in session.scalars(select(Phase).order_by(Phase.opens_at)).all():
            if is_open(phase):
                quotas += [
                    QuotaOut(
                        phase=phase.name, quota=u.name, limit=u.limit, used=u.used, resets_at=u.resets_at
                    )
                    for u in quota_usage(session, team.id, phase)
                ]
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


@router.get("/published/{submission_id}/tokens", tags=["published"])
def published_token_rows(
    session: SessionDep, submission_id: RowId, version: VersionName = DEFAULT_VERSION
) -> list[TokenRow]:
    """Per-token results of a published entry."""
    submission = published_submission(session, submission_id)
    return token_result_views(session, submission, version, only_failed=False, admin=False)


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
) -> Response:
    """The drill-down picture of a published entry on one token (splits whose scenes are public only)."""
    submission = published_submission(session, submission_id)
    settings = request.app.state.settings
    picture = scene_picture(submission, token, version, seed, admin=False, settings=settings)
    return Response(picture, media_type="image/png")
