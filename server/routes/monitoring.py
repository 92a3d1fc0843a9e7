"""GET /metrics (Prometheus' usual path): the service's figures (server.services.monitoring)."""

from __future__ import annotations

import logging
from collections.abc import Iterator

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.core import Metric

from server.auth import SessionDep
from server.queue import waiting_tasks
from server.services.monitoring import service_figures

log = logging.getLogger(__name__)
router = APIRouter()


class _Collected:
    """The metric families of one scrape, as a collector for a registry of its own."""

    def __init__(self, families: list[Metric]) -> None:
        self.families = families

    def collect(self) -> Iterator[Metric]:
        yield from self.families


@router.get("/metrics", include_in_schema=False)
def scrape(request: Request, session: SessionDep) -> Response:
    """Runs by status, failures by kind, chunks, worker deaths, scoring time, tokens/s, workers, queue depth."""
    try:
        depth: int | None = waiting_tasks(request.app.state.settings)
    except Exception:
        log.warning("queue depth unavailable", exc_info=True)
        depth = None
    registry = CollectorRegistry()
    registry.register(_Collected(list(service_figures(session, depth))))
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)
