"""Request bodies refused while they stream: past the upload limit, 413 naming the limit, and no byte more read.

Starlette spools an uploaded file to disk as it parses the form, so a size check after parsing (in the
route) would read and write a 10 GB upload in full first. This middleware answers at once a request whose
Content-Length is over the limit, and counts the bytes of any other as they arrive, stopping at the limit.
(Starlette's own RequestBodyLimitMiddleware does the counting too, but answers a declared length with a
plain "Content Too Large" that cannot say what the limit is.)
"""

from __future__ import annotations

from collections.abc import Callable

from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

# Room for the multipart boundaries and the metadata fields around the file in an upload's body.
FORM_OVERHEAD_BYTES = 64 * 1024


def upload_too_large(limit: int) -> str:
    """Return the message of an upload refused for its size (while streaming, or as a file)."""
    return (
        f"the upload is larger than the limit of {limit} bytes ({limit / 2**20:.0f} MiB); nothing was stored"
    )


class BodySizeLimit:
    """Refuse request bodies over `upload_limit()` + FORM_OVERHEAD_BYTES with 413, reading no further."""

    def __init__(self, app: ASGIApp, upload_limit: Callable[[], int]) -> None:
        self.app, self.upload_limit = app, upload_limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.upload_limit()
        declared = Headers(scope=scope).get("content-length", "")
        if declared.isdigit() and int(declared) > limit + FORM_OVERHEAD_BYTES:
            response = JSONResponse(
                {"detail": upload_too_large(limit)}, status_code=413, headers={"Connection": "close"}
            )
            await response(scope, receive, send)
            return
        received = 0

        async def counted() -> Message:
            nonlocal received
            message = await receive()
            received += len(message.get("body", b""))
            if received > limit + FORM_OVERHEAD_BYTES:
                # An HTTPException passes FastAPI's form parsing untouched and reaches the 413 handler.
                raise HTTPException(status_code=413, detail=upload_too_large(limit))
            return message

        await self.app(scope, counted, send)
