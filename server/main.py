"""The FastAPI application: `create_app(settings)` wires database, routes, web pages and error mapping."""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import partial
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler, request_validation_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from pydantic import TypeAdapter
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError, InterfaceError, OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException

from scorer import ENGINE_VERSION
from server.body_limit import BodySizeLimit
from server.db import make_engine, make_session_factory, transaction
from server.migrate import require_migrated
from server.models import Split
from server.object_store import StoreUnavailable, connect
from server.queue import broker_status, enqueue_submission, live_workers
from server.rate_limits import RateLimits
from server.routes import admin, monitoring, public, submissions, web
from server.services.admin import add_split
from server.services.errors import ServiceError
from server.settings import Settings, get_settings
from server.ttl_cache import TTLCache
from server.upload_gate import UploadGate

log = logging.getLogger(__name__)
API_PREFIX = "/api/v1"


def _answers_json(request: Request) -> bool:
    """Whether a path is the API's (JSON errors, as its clients parse them) rather than a page's."""
    return request.url.path.startswith(("/api/", "/metrics"))


def _service_error(request: Request, error: Exception) -> Response:
    assert isinstance(error, ServiceError)
    retry_after = error.retry_after_s()
    headers = {} if retry_after is None else {"Retry-After": str(retry_after)}
    if not _answers_json(request):
        return web.error_page(request, error.http_status, error.message, headers)
    return JSONResponse(
        # pydantic's JSON mode, as for every response model: UTC times end in "Z".
        TypeAdapter(Any).dump_python({"detail": error.message, **error.extra}, mode="json"),
        status_code=error.http_status,
        headers=headers,
    )


DATABASE_DOWN = "the database is not answering right now; nothing was changed, try again in a few seconds"
STORE_DOWN = (
    "the file store is not answering right now; nothing was stored and no submission was created, "
    "upload the file again in a minute"
)
OUTAGE_RETRY_AFTER_S = 5


def _outage(message: str) -> Callable[[Request, Exception], Response]:
    """Return the handler of an outage (the database's, the object store's): a 503 the client may retry, not
    a 500, since the transaction was rolled back and no row names what was not stored."""

    def answer(request: Request, error: Exception) -> Response:
        log.error("outage during %s %s: %s", request.method, request.url.path, error)
        headers = {"Retry-After": str(OUTAGE_RETRY_AFTER_S)}
        if _answers_json(request):
            return JSONResponse({"detail": message}, status_code=503, headers=headers)
        return web.error_page(request, 503, f"NAVSIM Leaderboard: {message}.", headers)

    return answer


async def _http_error(request: Request, error: Exception) -> Response:
    """A page the product does not have is a 404 page; the API keeps FastAPI's JSON answer."""
    assert isinstance(error, StarletteHTTPException)
    if _answers_json(request):
        return await http_exception_handler(request, error)
    message = (
        f"There is no page at {request.url.path}."
        if error.status_code == 404
        else f"{request.method} {request.url.path}: {error.detail}."
    )
    return web.error_page(request, error.status_code, message, dict(error.headers or {}))


async def _invalid_request(request: Request, error: Exception) -> Response:
    """A page's path that does not parse (/submissions/abc) names no page: 404; the API lists the problems."""
    assert isinstance(error, RequestValidationError)
    if _answers_json(request):
        return await request_validation_exception_handler(request, error)
    return web.error_page(request, 404, f"There is no page at {request.url.path}.")


def register_configured_splits(app: FastAPI) -> None:
    """Register the splits named in the settings that are not registered yet, and queue their baselines."""
    settings: Settings = app.state.settings
    for name, directory in settings.splits.items():
        try:
            with transaction(app.state.session_factory) as session:
                if session.scalar(select(Split.id).where(Split.name == name)) is not None:
                    continue
                split, baselines = add_split(
                    session, None, name, directory, None, False, settings.submission_store
                )
                queued = [submission.id for submission in baselines]
        except IntegrityError:
            continue  # another API process registered it at the same moment
        log.info("registered split %s (%s tokens) from %s", name, split.token_count, directory)
        for submission_id in queued:
            app.state.enqueue(submission_id)


def create_app(settings: Settings | None = None, enqueue: Callable[[int], None] | None = None) -> FastAPI:
    """Return the API and web app on a migrated database; raises NotMigratedError (with the fix) otherwise."""
    settings = settings or get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    if not settings.storage_url:
        settings.storage_dir.mkdir(parents=True, exist_ok=True)
    engine = make_engine(settings.database_url)
    require_migrated(engine)

    # fastapi-offline serves Swagger UI's and ReDoc's assets itself: /docs and /redoc need no CDN.
    app = FastAPIOffline(
        favicon_url="/static/favicon.svg",
        title="NAVSIM Leaderboard",
        version=ENGINE_VERSION,
        description=(
            "Submissions, leaderboard (PDM Score v1.0 and v1.1, Extended PDM Score v2.2) and administration"
            " of the NAVSIM benchmark."
        ),
    )
    app.state.settings = settings
    app.state.engine = engine
    app.state.session_factory = make_session_factory(engine)
    app.state.enqueue = enqueue or partial(enqueue_submission, settings=settings)
    app.state.broker_status = broker_status
    app.state.live_workers = live_workers
    app.state.leaderboard_cache = TTLCache(settings.leaderboard_cache_seconds)
    app.state.page_cache = TTLCache(
        settings.leaderboard_cache_seconds
    )  # the board's page (server.routes.web)
    app.state.rate_limits = RateLimits(settings.rate_limit_storage)
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _invalid_request)
    app.add_middleware(BodySizeLimit, upload_limit=lambda: app.state.settings.max_upload_bytes)
    # Outermost: an upload with a wrong token is refused before anything reads its body.
    upload_checks = {API_PREFIX + path: check for path, check in submissions.UPLOAD_CHECKS.items()}
    app.add_middleware(UploadGate, checks=upload_checks)
    for outage in (OperationalError, InterfaceError):
        app.add_exception_handler(outage, _outage(DATABASE_DOWN))
    app.add_exception_handler(StoreUnavailable, _outage(STORE_DOWN))
    app.include_router(public.router, prefix=API_PREFIX)
    app.include_router(submissions.router, prefix=API_PREFIX)
    app.include_router(admin.router, prefix=API_PREFIX)
    app.include_router(web.router)
    app.include_router(monitoring.router)
    app.mount("/static", StaticFiles(directory=web.WEB_DIR / "static"), name="static")
    register_configured_splits(app)
    connect(settings.submission_store)
    return app


def app_from_environment() -> FastAPI:
    """Return the app configured from the environment (the uvicorn factory of `navsim-lb serve`)."""
    return create_app(get_settings())
