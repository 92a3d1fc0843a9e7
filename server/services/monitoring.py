"""Operational figures for Prometheus, read from the SQL record at each scrape.

The API and the workers are many processes on many machines: the database is the one place that knows every
run, chunk and worker, so a scrape of any API process gives the whole service, and nothing is lost when a
process restarts. Only the queue depth comes from the broker.
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.models import ChunkState, FailureKind, Result, ScoringChunk, Status, Submission, utc_now
from server.services.workers import workers_from_heartbeats

RATE_WINDOW_S = 600.0  # tokens per second over the runs aggregated in the last ten minutes


def _gauge(name: str, documentation: str, label: str, counts: dict[Any, int], every: list[str]) -> Metric:
    gauge = GaugeMetricFamily(name, documentation, labels=[label])
    for value in every:
        gauge.add_metric([value], counts.get(value, 0))
    return gauge


def service_figures(session: Session, queue_depth: int | None) -> Iterator[Metric]:
    """Yield the service's figures as Prometheus metric families.

    Runs by status, failures by kind, chunks, deaths, scoring time, workers.
    """
    statuses = dict(
        session.execute(select(Submission.status, func.count()).group_by(Submission.status)).all()
    )
    yield _gauge(
        "navsim_lb_runs", "Submissions by the status of their current run", "status", statuses, list(Status)
    )
    failures = dict(
        session.execute(
            select(Submission.failure_kind, func.count())
            .where(Submission.status == Status.failed)
            .group_by(Submission.failure_kind)
        ).all()
    )
    yield _gauge(
        "navsim_lb_failed_runs",
        "Failed runs by kind (infrastructure ones are refunded)",
        "kind",
        failures,
        list(FailureKind),
    )
    chunks = dict(
        session.execute(select(ScoringChunk.state, func.count()).group_by(ScoringChunk.state)).all()
    )
    yield _gauge("navsim_lb_chunks", "Scoring chunks by state", "state", chunks, list(ChunkState))
    deaths = CounterMetricFamily(
        "navsim_lb_chunk_deaths", "Worker processes that died while scoring a chunk (kills, crashes, OOM)"
    )
    deaths.add_metric([], session.scalar(select(func.coalesce(func.sum(ScoringChunk.deaths), 0))) or 0)
    yield deaths
    scored = select(
        func.coalesce(func.sum(Result.duration_s), 0.0), func.coalesce(func.sum(Result.tokens), 0)
    )
    scored = scored.where(Result.subset == "all")
    seconds, tokens = session.execute(scored).one()
    scoring = CounterMetricFamily(
        "navsim_lb_scoring_seconds", "Seconds spent scoring the runs aggregated so far"
    )
    scoring.add_metric([], float(seconds))
    yield scoring
    scored_tokens = CounterMetricFamily(
        "navsim_lb_scored_tokens", "Token results (per version and seed) aggregated"
    )
    scored_tokens.add_metric([], int(tokens))
    yield scored_tokens
    since = utc_now() - timedelta(seconds=RATE_WINDOW_S)
    recent_seconds, recent_tokens = session.execute(scored.where(Result.created_at >= since)).one()
    rate = GaugeMetricFamily(
        "navsim_lb_tokens_per_second",
        "Token results per scoring second, over runs aggregated in the last 10 minutes",
    )
    rate.add_metric([], float(recent_tokens) / recent_seconds if recent_seconds else 0.0)
    yield rate
    workers = GaugeMetricFamily("navsim_lb_workers", "Workers that wrote a heartbeat recently")
    workers.add_metric([], workers_from_heartbeats(session)["count"])
    yield workers
    if queue_depth is not None:
        queue = GaugeMetricFamily(
            "navsim_lb_queue_depth", "Tasks waiting in the broker's queue, taken by no worker"
        )
        queue.add_metric([], queue_depth)
        yield queue
