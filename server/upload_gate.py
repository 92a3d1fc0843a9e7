"""Uploads authorised from their headers, before their body is read.

FastAPI parses a multipart form (spooling the file) before a route's dependencies run, so a missing or wrong
token would be refused only once the whole upload was received. This middleware runs the upload routes' own
token checks (server.auth) on the request's headers and answers a refusal (401, 403, 429, 503) without reading
a byte of the body; an accepted request goes on, and the route's dependencies check again as for any route.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping

from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import Response
from starlette.types import ASGIApp, Receive, Scope, Send

# What a route requires of the request's token: raises the route's refusal, or returns.
Check = Callable[[Request, Session], object]


class UploadGate:
    """Run `checks[path]` on the headers of a POST to `path` before anything reads its body."""

    def __init__(self, app: ASGIApp, checks: Mapping[str, Check]) -> None:
        self.app, self.checks = app, checks

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        check = (
            self.checks.get(scope["path"]) if scope["type"] == "http" and scope["method"] == "POST" else None
        )
        if check is None:
            await self.app(scope, receive, send)
            return
        request = Request(scope)  # no receive: reading the body from it would fail
        try:
            await run_in_threadpool(_run, check, request)
        except Exception as refusal:  # noqa: BLE001 - answered by the app's own handler, or raised again
            response = await _handled(request, refusal)
            # The client may still be sending the body, which is never read: the connection cannot be reused.
            response.headers["Connection"] = "close"
            await response(scope, receive, send)
            return
        await self.app(scope, receive, send)


def _run(check: Check, request: Request) -> None:
    with request.app.state.session_factory() as session:
        check(request, session)


async def _handled(request: Request, error: Exception) -> Response:
    """Return the answer the app's exception handlers give `error` (as if a route raised it); raise it if none."""
    handlers = request.app.exception_handlers
    handler = next((handlers[kind] for kind in type(error).__mro__ if kind in handlers), None)
    if handler is None:
        raise error
    response = handler(request, error)
    return await response if inspect.isawaitable(response) else response
