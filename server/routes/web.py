"""Web pages: the public leaderboard (server-rendered) and the admin dashboard (a page calling the admin API)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse
from fastapi.templating import Jinja2Templates
from sqlalchemy import select

from scorer.versions import DEFAULT_VERSION, METRIC_LABELS, VERSIONS
from server.auth import SessionDep
from server.models import Phase
from server.routes.public import cached_board
from server.services.errors import ServiceError

TEMPLATES = Jinja2Templates(directory=Path(__file__).resolve().parent.parent.parent / "web" / "templates")
router = APIRouter(include_in_schema=False)


@router.get("/", response_class=HTMLResponse)
def leaderboard_page(
    request: Request,
    session: SessionDep,
    version: str = DEFAULT_VERSION,
    subset: str | None = None,
    sort: str = "score",
    phase: str | None = None,
) -> HTMLResponse:
    """The public leaderboard."""
    context: dict[str, Any] = {
        "versions": list(VERSIONS),
        "phases": [p.name for p in session.scalars(select(Phase).order_by(Phase.opens_at.desc())).all()],
        "labels": METRIC_LABELS,
        "query": {"version": version, "subset": subset, "sort": sort, "phase": phase},
    }
    status = 200
    try:
        context["board"] = cached_board(request.app, version, subset, sort, phase).view
    except ServiceError as error:
        context["error"] = error.message
        status = error.http_status
    return TEMPLATES.TemplateResponse(request, "leaderboard.html", context, status_code=status)


@router.get("/admin", response_class=HTMLResponse)
def admin_page(request: Request) -> HTMLResponse:
    """The admin dashboard; it holds no data itself and asks the admin API with the token typed in."""
    return TEMPLATES.TemplateResponse(request, "admin.html", {"versions": list(VERSIONS)})
