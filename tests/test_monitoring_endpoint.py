"""GET /metrics: Prometheus text with the whole service's figures, read from SQL (runs by status, failures by
kind, chunks by state, worker deaths, scoring seconds and tokens, workers) and the broker's queue depth."""

from __future__ import annotations

from prometheus_client.parser import text_string_to_metric_families
from server_testing import World, claimed_submission, submit_scored, uniform

from server.db import transaction
from server.models import FailureKind, Submission
from server.runs import mark_failed
from server.runs._plan import plan_chunks


def _samples(world: World) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    response = world.client.get("/metrics")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain")
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(response.text)
        for sample in family.samples
    }


def test_monitoring_counts_runs_failures_chunks_and_scoring(world: World) -> None:
    submit_scored(
        world, world.team_id, b"scored", [uniform(0.5)]
    )  # 3 chunks of 0.5 s per version, 3 versions
    failed = claimed_submission(world, b"failed").id
    running = claimed_submission(world, b"running").id
    with transaction(world.factory) as session:
        mark_failed(session, failed, 1, FailureKind.infrastructure, "a worker was lost")
        plan_chunks(session, session.get(Submission, running), ["a", "b", "c"], 2)

    samples = _samples(world)
    assert samples[("navsim_lb_runs", (("status", "scored"),))] == 1
    assert samples[("navsim_lb_runs", (("status", "running"),))] == 1
    assert samples[("navsim_lb_runs", (("status", "queued"),))] == 0
    assert samples[("navsim_lb_failed_runs", (("kind", "infrastructure"),))] == 1
    assert samples[("navsim_lb_chunks", (("state", "queued"),))] == 2
    assert samples[("navsim_lb_chunk_deaths_total", ())] == 0
    assert samples[("navsim_lb_scored_tokens_total", ())] == 3 * 40  # three versions x 40 tokens
    assert samples[("navsim_lb_scoring_seconds_total", ())] == 3 * 3 * 0.5
    assert samples[("navsim_lb_tokens_per_second", ())] == 120 / 4.5
    assert samples[("navsim_lb_queue_depth", ())] == 0  # the embedded broker, where the test sent nothing
    assert ("navsim_lb_workers", ()) in samples
