"""The chunk record the reaper holds the broker to: planning skips tokens in flight, only a queued chunk starts
(a duplicate message drops), a stopped beat is a death, a death splits a chunk one token per chunk, a single
token with a death is scored isolated, workers lost again and again fail the run; a chunk sent long ago and
still queued is forgotten."""

from __future__ import annotations

from datetime import datetime, timedelta

from server_testing import REFERENCE_DIR, World, claimed_submission, reference_tokens

from scorer.evaluate import pairing_contexts
from scorer.scene import scene_start
from server.db import transaction
from server.models import ChunkState, FailureKind, ScoringChunk, Status, Submission, utc_now
from server.runs import LOST_DEATHS, StartAction, beat_chunk, cancel, reap_dead_chunks, start_chunk
from server.runs._chunks import dead_chunks, forgotten_chunks, resend_chunk
from server.runs._finish import live_chunks
from server.runs._plan import plan_chunks
from server.runs._rows import finish_chunk
from server.services.splits import scene_starts
from server.services.workers import LIVE_WITHIN_S

# In the order chunks take them: by log, then start time (scene_starts).
PROBES = REFERENCE_DIR.parent / "epdms" / "probes"
TOKENS = sorted(
    reference_tokens(), key=lambda token: (scene_start(REFERENCE_DIR / "scenes" / f"{token}.json.gz"), token)
)


def _chunk(world: World, chunk_id: int) -> ScoringChunk:
    with world.session() as session:
        chunk = session.get(ScoringChunk, chunk_id)
        assert chunk is not None
        return chunk


def _plan(world: World, submission: Submission, tokens: list[str], size: int) -> list[int]:
    with transaction(world.factory) as session:
        return plan_chunks(session, session.get(Submission, submission.id), tokens, size)


def _start(world: World, chunk_id: int, worker: str, now: datetime | None = None) -> StartAction:
    with transaction(world.factory) as session:
        return start_chunk(session, chunk_id, 1, worker, now).action


def _kill(world: World, chunk_id: int, started: datetime) -> list[int]:
    """Let the chunk's process stop beating and the reaper find it: return the dead chunks it re-sends."""
    with transaction(world.factory) as session:
        dead = dead_chunks(session, started + timedelta(seconds=LIVE_WITHIN_S + 1))
        return [resend_chunk(session, chunk, died=True) for chunk in dead if chunk.id == chunk_id]


def test_planning_skips_the_tokens_live_chunks_hold(world: World) -> None:
    submission = claimed_submission(world, b"plan")
    first = _plan(world, submission, TOKENS[:5], 2)
    assert [_chunk(world, chunk).tokens for chunk in first] == [TOKENS[:2], TOKENS[2:4], TOKENS[4:5]]
    # Planned again (a duplicate claim): only the tokens no live chunk holds get chunks.
    again = _plan(world, submission, TOKENS[:7], 2)
    assert [_chunk(world, chunk).tokens for chunk in again] == [TOKENS[5:7]]
    with transaction(world.factory) as session:
        finish_chunk(session, first[0])
        assert live_chunks(session, submission.id, 1) == 3
    assert [_chunk(world, chunk).tokens for chunk in _plan(world, submission, TOKENS[:2], 2)] == [TOKENS[:2]]


def test_only_a_queued_chunk_of_the_current_run_starts(world: World) -> None:
    submission = claimed_submission(world, b"start")
    chunk_id, other = _plan(world, submission, TOKENS[:4], 2)
    assert _start(world, chunk_id, "host/1") == StartAction.score
    assert _start(world, chunk_id, "host/2") == StartAction.drop  # a duplicate message while it runs
    started = _chunk(world, chunk_id)
    assert (started.state, started.worker, started.starts) == (ChunkState.running, "host/1", 1)
    with transaction(world.factory) as session:
        assert beat_chunk(session, chunk_id, "host/1")
        assert not beat_chunk(session, chunk_id, "host/2")  # not its chunk
        finish_chunk(session, chunk_id)
        assert not beat_chunk(session, chunk_id, "host/1")
        assert start_chunk(session, 10_000, 1, "host/1").action == StartAction.drop  # no such chunk
        cancel(session, session.get(Submission, submission.id))
    assert _start(world, other, "host/1") == StartAction.drop  # the run is no longer wanted


def test_a_stopped_beat_is_a_death_and_a_death_splits_then_isolates(world: World) -> None:
    submission = claimed_submission(world, b"isolated")
    (chunk_id,) = _plan(world, submission, TOKENS[:3], 3)
    started = utc_now()
    assert _start(world, chunk_id, "host/1", started) == StartAction.score
    with world.session() as session:  # beating: alive
        assert dead_chunks(session, started + timedelta(seconds=LIVE_WITHIN_S - 1)) == []
    assert _kill(world, chunk_id, started) == [chunk_id]
    died = _chunk(world, chunk_id)
    assert (died.state, died.deaths) == (ChunkState.queued, 1)

    with transaction(world.factory) as session:
        split = start_chunk(session, chunk_id, 1, "host/2")
    assert split.action == StartAction.split_up and len(split.children) == 3
    assert _chunk(world, chunk_id).state == ChunkState.split_up
    children = [_chunk(world, child) for child in split.children]
    assert [(child.tokens, child.deaths) for child in children] == [([token], 1) for token in TOKENS[:3]]

    # Each single token starts again, to be scored in a process of its own; a worker lost while it does is one
    # more death, and the token starts isolated again.
    lost, died = split.children[1:]
    started = utc_now()
    with transaction(world.factory) as session:
        verdict = start_chunk(session, lost, 1, "host/3", started)
    assert (verdict.action, verdict.tokens, verdict.isolated) == (StartAction.score, (TOKENS[1],), True)
    assert _kill(world, lost, started) == [lost]
    with transaction(world.factory) as session:
        verdict = start_chunk(session, lost, 1, "host/4")
    assert (verdict.action, verdict.isolated, _chunk(world, lost).deaths) == (StartAction.score, True, 2)
    # The isolated process died: its token is written as failed, the chunk finished with that death on record.
    assert _start(world, died, "host/5") == StartAction.score
    with transaction(world.factory) as session:
        finish_chunk(session, died, ChunkState.failed)
    assert (_chunk(world, died).state, _chunk(world, died).deaths) == (ChunkState.failed, 2)
    # A chunk without a death is scored where it is taken.
    (fresh,) = _plan(world, submission, TOKENS[3:4], 1)
    with transaction(world.factory) as session:
        assert not start_chunk(session, fresh, 1, "host/6").isolated


def test_a_chunk_whose_workers_are_lost_again_and_again_fails_its_run_refunded(world: World) -> None:
    """Kills from outside never fail a token; but a chunk whose worker is lost LOST_DEATHS times is not the
    team's doing: its run fails, not charged, naming what happened."""
    submission = claimed_submission(world, b"lost")
    (chunk_id,) = _plan(world, submission, TOKENS[:1], 1)
    for death in range(1, LOST_DEATHS + 1):
        started = utc_now()
        assert _start(world, chunk_id, f"host/{death}", started) == StartAction.score
        with transaction(world.factory) as session:
            reaped = reap_dead_chunks(session, started + timedelta(seconds=LIVE_WITHIN_S + 1), 3600.0)
        if death < LOST_DEATHS:
            assert (reaped.chunks, reaped.failed) == ([(submission.id, 1, chunk_id)], [])
            assert _chunk(world, chunk_id).deaths == death
    assert (reaped.chunks, reaped.failed) == ([], [submission.id])
    with world.session() as session:
        failed = session.get(Submission, submission.id)
        assert failed is not None
        assert (failed.status, failed.failure_kind, failed.charged) == (
            Status.failed,
            FailureKind.infrastructure,
            False,
        )
        assert (failed.error or "").startswith(
            f"the workers scoring a part of this submission were lost {LOST_DEATHS} times"
        )
        assert f"chunk {chunk_id} of 1 tokens" in (failed.error_detail or "")


def test_a_chunk_queued_since_before_the_cut_is_forgotten(world: World) -> None:
    submission = claimed_submission(world, b"forgotten")
    queued, running = _plan(world, submission, TOKENS[:4], 2)
    _start(world, running, "host/1")
    with world.session() as session:
        assert forgotten_chunks(session, utc_now() - timedelta(seconds=30)) == []
        assert [chunk.id for chunk in forgotten_chunks(session, utc_now() + timedelta(seconds=1))] == [queued]
    with transaction(world.factory) as session:
        (chunk,) = forgotten_chunks(session, utc_now() + timedelta(seconds=1))
        resend_chunk(session, chunk, died=False)
    assert _chunk(world, queued).deaths == 0  # lost by the broker is not a death


def test_chunks_carry_the_earlier_frames_they_pair_with_and_so_do_the_chunks_of_a_split(world: World) -> None:
    """v2.2's EC pairs a frame with the one 0.5 s earlier in its log: a chunk takes consecutive frames of a log,
    and carries the earlier frames that other chunks hold (its context); split one token per chunk after a
    death, each child carries its own, its former neighbours among them."""
    submission = claimed_submission(world, b"contexts")
    with transaction(world.factory) as session:
        split = session.get(Submission, submission.id).split
        split.directory = str(PROBES)  # twins 0.5 s and 1 s apart in one log
        starts = scene_starts(session, split)
    chunk_ids = _plan(world, submission, sorted(starts), 5)
    chunks = [_chunk(world, chunk_id) for chunk_id in chunk_ids]
    assert [chunk.context for chunk in chunks] == pairing_contexts(starts, [chunk.tokens for chunk in chunks])
    alone = pairing_contexts(starts, [[token] for chunk in chunks for token in chunk.tokens])
    assert 0 < sum(map(len, (chunk.context for chunk in chunks))) < sum(map(len, alone))

    chunk = next(
        chunk
        for chunk in chunks
        if any(
            set(context) & set(chunk.tokens)
            for context in pairing_contexts(starts, [[token] for token in chunk.tokens])
        )
    )
    started = utc_now()
    assert _start(world, chunk.id, "host/1", started) == StartAction.score
    assert _kill(world, chunk.id, started) == [chunk.id]
    with transaction(world.factory) as session:
        split_up = start_chunk(session, chunk.id, 1, "host/2")
    children = [_chunk(world, child) for child in split_up.children]
    assert [child.context for child in children] == pairing_contexts(starts, [[t] for t in chunk.tokens])
    assert any(set(child.context) & set(chunk.tokens) for child in children)
    with transaction(world.factory) as session:
        assert start_chunk(session, children[0].id, 1, "host/3").context == tuple(children[0].context)
