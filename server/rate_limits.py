"""Rate limits on what an attacker repeats: failed authentications per client address, uploads per token and
per client address, each a 429 with Retry-After once used up.

The counting is the `limits` library's moving window, in this process's memory by default (one API process,
the embedded setup) or in Redis when RATE_LIMIT_STORAGE is a redis:// URL, so that every API process of a
deployment shares the counts. Quotas (server.services.quota) decide what a team may submit; these limits
only stop floods and token guessing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from limits import RateLimitItem, parse
from limits.storage import storage_from_string
from limits.strategies import MovingWindowRateLimiter

from server.services.errors import ServiceError


class RateLimited(ServiceError):
    """Too many attempts of one kind from one client: retry after `retry_after_s` seconds."""

    http_status = 429

    def __init__(self, message: str, wait_s: int) -> None:
        super().__init__(message, retry_after_s=wait_s)
        self.wait_s = wait_s

    def retry_after_s(self) -> int | None:
        return self.wait_s


@dataclass(frozen=True)
class Limit:
    rate: RateLimitItem
    what: str  # how the message names what was repeated


FAILED_AUTHENTICATIONS = Limit(parse("20/minute"), "failed authentications from your address")
UPLOADS_PER_TOKEN = Limit(parse("30/minute"), "uploads with this token")
UPLOADS_PER_ADDRESS = Limit(parse("60/minute"), "uploads from your address")


class RateLimits:
    """Moving-window counters in the storage `storage_uri` names (memory://, redis://host:port/db)."""

    def __init__(self, storage_uri: str) -> None:
        self._limiter = MovingWindowRateLimiter(storage_from_string(storage_uri))

    def _refusal(self, limit: Limit, key: str) -> RateLimited:
        reset_at = self._limiter.get_window_stats(limit.rate, limit.what, key).reset_time
        wait = max(1, int(reset_at - time.time()) + 1)
        return RateLimited(f"too many {limit.what} ({limit.rate}): try again in {wait} s", wait)

    def check(self, limit: Limit, key: str) -> None:
        """Raise RateLimited if `limit` is used up for `key` (without counting this request)."""
        if not self._limiter.test(limit.rate, limit.what, key):
            raise self._refusal(limit, key)

    def hit(self, limit: Limit, key: str) -> None:
        """Count one attempt for `key`; raise RateLimited if it is one too many."""
        if not self._limiter.hit(limit.rate, limit.what, key):
            raise self._refusal(limit, key)
