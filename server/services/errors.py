"""Errors the services raise; the API maps each kind to one HTTP status."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any


class ServiceError(Exception):
    """Base of the errors a request can cause; `message` is safe to show to the caller."""

    http_status = 400

    def __init__(self, message: str, **extra: Any) -> None:
        super().__init__(message)
        self.message = message
        self.extra = extra

    def retry_after_s(self) -> int | None:
        """Seconds after which the same request may succeed (the Retry-After header), if that is known."""
        return None


class NotFound(ServiceError):
    """The object does not exist (or the caller may not see it)."""

    http_status = 404


class Forbidden(ServiceError):
    """The caller is authenticated but not allowed to do this."""

    http_status = 403


class Conflict(ServiceError):
    """The request contradicts stored state (duplicate file, reused idempotency key, wrong status)."""

    http_status = 409


class Invalid(ServiceError):
    """The request is malformed; `problems` lists every problem as token/field/message."""

    http_status = 422

    def __init__(self, message: str, problems: list[dict[str, str | None]]) -> None:
        super().__init__(message, problems=problems)
        self.problems = problems


class QuotaExceeded(ServiceError):
    """A quota of the team in the phase is used up until `resets_at` (None: it never resets by itself)."""

    http_status = 429

    def __init__(self, quota: str, limit: int, used: int, resets_at: datetime | None, message: str) -> None:
        super().__init__(message, quota=quota, limit=limit, used=used, resets_at=resets_at)
        self.quota = quota
        self.limit = limit
        self.used = used
        self.resets_at = resets_at

    def retry_after_s(self) -> int | None:
        if self.resets_at is None:
            return None
        return max(1, int((self.resets_at - datetime.now(UTC)).total_seconds()))
