"""Web pages: the public leaderboard (server-rendered) and the admin dashboard (a page calling the admin API)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from importlib.resources import files
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from fastapi.templating import Jinja2Templates

from scorer.ec_undefined import NO_TOKEN_PAIRED
from scorer.submission import MAX_SEEDS
from scorer.versions import (
    ALL_RESULT_COLUMNS,
    DEFAULT_VERSION,
    METRIC_LABELS,
    OFFICIAL_REPOSITORY,
    TWO_STAGE_VERSIONS,
    VERSIONS,
    VersionName,
)
from server.auth import SessionDep
from server.numbers import counted, percent
from server.params import RowId
from server.runs import BOARD_VERSIONS
from server.services.errors import ServiceError
from server.services.integrity_checks import integrity_thresholds
from server.services.leaderboard import cached_board
from server.services.rules import PAPERS, SUBSCORES, all_version_rules, header_title, subscore
from server.services.splits import list_phases
from server.services.submissions import get_submission

# Templates and static assets are package data of `server.web`: the same lookup in a checkout and a wheel.
WEB_DIR = Path(str(files("server.web")))
TEMPLATES = Jinja2Templates(directory=WEB_DIR / "templates")
TEMPLATES.env.filters["percent"] = percent  # the one rounding of every figure (server.numbers)
TEMPLATES.env.globals["counted"] = counted
TEMPLATES.env.globals["header_title"] = header_title  # a board header's full name and meaning
TEMPLATES.env.globals["subscore"] = subscore
router = APIRouter(include_in_schema=False)
SCORE_LABELS = {name: VERSIONS[name].score_label for name in BOARD_VERSIONS}  # PDMS or EPDMS per version


PAGE_TITLES = {404: "Page not found", 403: "Not allowed", 503: "Unavailable"}


def error_page(
    request: Request, status: int, message: str, headers: dict[str, str] | None = None
) -> HTMLResponse:
    """Return the page that says what went wrong (the API's routes answer JSON instead)."""
    context = {"title": PAGE_TITLES.get(status, "Something went wrong"), "message": message}
    return TEMPLATES.TemplateResponse(request, "error.html", context, status_code=status, headers=headers)


@dataclass(frozen=True)
class Page:
    """A rendered page, kept for the leaderboard's cache period (`app.state.page_cache`)."""

    body: bytes
    status: int


@router.get("/", response_class=HTMLResponse)
async def leaderboard_page(
    request: Request,
    version: str | None = None,
    subset: str | None = None,
    phase: str | None = None,
) -> HTMLResponse:
    """The public leaderboard: tabs per phase, metric version and subset; the table sorts in the browser.

    Rendered once per cache period and query, like the board it shows (server.ttl_cache says how): the page
    is read as often as the board, and rendering it took ten times the board's cost in the API's CPU. Its
    links are absolute, so the address it was asked at is part of the key."""
    cache = request.app.state.page_cache
    key = (str(request.base_url), version, subset, phase)
    page = cache.get(key)
    if page is None:  # the database is only asked off the event loop
        render = partial(_leaderboard_page, request, version, subset, phase)
        page = await run_in_threadpool(cache.get_or_compute, key, render)
    return HTMLResponse(page.body, status_code=page.status)


def _leaderboard_page(request: Request, version: str | None, subset: str | None, phase: str | None) -> Page:
    query = {"version": version, "subset": subset, "phase": phase}

    def here(**changes: str | None) -> str:
        """Return the query string of this page with `changes` applied (None drops a parameter)."""
        return "?" + urlencode({k: v for k, v in (query | changes).items() if v is not None})

    state = request.app.state
    with state.session_factory() as session:
        phases = [phase.name for phase in list_phases(session, newest_first=True)]
    context: dict[str, Any] = {
        "versions": list(BOARD_VERSIONS),
        "score_labels": SCORE_LABELS,
        "phases": phases,
        "labels": METRIC_LABELS,
        "query": query,
        "here": here,
        "ddc_role": VERSIONS[VersionName(version)].ddc_role if version in VERSIONS else "",
        "ec_undefined": NO_TOKEN_PAIRED,
    }
    status = 200
    try:
        board = cached_board(
            state.leaderboard_cache, state.session_factory, version, subset, "score", phase
        ).view
        context["board"] = board
        context["versions"] = board["versions"]
        context["ddc_role"] = VERSIONS[VersionName(board["version"])].ddc_role
        query["phase"], query["subset"], query["version"] = board["phase"], board["subset"], board["version"]
    except ServiceError as error:
        context["error"] = error.message
        status = error.http_status
    response = TEMPLATES.TemplateResponse(request, "leaderboard.html", context, status_code=status)
    return Page(bytes(response.body), response.status_code)


@router.get("/rules", response_class=HTMLResponse)
def rules_page(request: Request) -> HTMLResponse:
    """The rules: each metric version's subscores, formula, weights and official code; seeds, ties, papers."""
    context = {
        "subscores": SUBSCORES,
        "versions": all_version_rules(),
        "papers": PAPERS,
        "repository": OFFICIAL_REPOSITORY,
        "max_seeds": MAX_SEEDS,
    }
    return TEMPLATES.TemplateResponse(request, "rules.html", context)


@router.get("/admin", response_class=HTMLResponse)
def admin_page(request: Request) -> HTMLResponse:
    """The admin dashboard; it holds no data itself and asks the admin API with the token typed in."""
    context = {"versions": list(BOARD_VERSIONS), "default_version": DEFAULT_VERSION}
    return TEMPLATES.TemplateResponse(request, "admin.html", context)


@router.get("/admin/integrity", response_class=HTMLResponse)
def integrity_page(request: Request) -> HTMLResponse:
    """The integrity checks' flags with their evidence, read with the organiser's token; the organiser decides."""
    return TEMPLATES.TemplateResponse(request, "integrity.html", {"thresholds": integrity_thresholds()})


@router.get("/admin/rescores/{rescore_id}", response_class=HTMLResponse)
def rescore_page(request: Request, rescore_id: RowId) -> HTMLResponse:
    """The rank-change report of a rescore, read with the organiser's token; it follows the runs to the end."""
    return TEMPLATES.TemplateResponse(request, "rescore.html", {"rescore_id": rescore_id})


@router.get("/team", response_class=HTMLResponse)
def team_page(request: Request) -> HTMLResponse:
    """Sign in or register; upload with live progress, history, metadata and final-entry choice (team API)."""
    page = {
        "versions": list(BOARD_VERSIONS),
        "two_stage_versions": list(TWO_STAGE_VERSIONS),  # shown with each stage's score
        "score_labels": SCORE_LABELS,
        "default_version": DEFAULT_VERSION,
    }
    return TEMPLATES.TemplateResponse(request, "team.html", {"page": page})


@router.get("/submissions/{submission_id}", response_class=HTMLResponse)
def submission_page(request: Request, session: SessionDep, submission_id: RowId) -> HTMLResponse:
    """One submission for its team: breakdown beside the baselines, histograms, worst tokens, a diff.
    The page reads it with the visitor's token; one that does not exist is a 404 page at once."""
    get_submission(session, submission_id)
    page = {
        "submission_id": submission_id,
        "versions": list(BOARD_VERSIONS),
        "score_labels": SCORE_LABELS,
        "default_version": DEFAULT_VERSION,
        "labels": METRIC_LABELS,
        "ddc_roles": {name: VERSIONS[name].ddc_role for name in BOARD_VERSIONS},
        "titles": {column: header_title(column) for column in ALL_RESULT_COLUMNS if column != "score"},
        "ec_undefined": NO_TOKEN_PAIRED,
    }
    return TEMPLATES.TemplateResponse(
        request, "submission.html", {"submission_id": submission_id, "page": page}
    )
