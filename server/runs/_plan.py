"""Planning a run: its tokens without rows become queued chunks, each with the frames it pairs with.

On a log-replay split a chunk takes consecutive frames of a log (the split's tokens in log and time order) so
that few of its tokens need a context to pair with (v2.2's two-frame comfort;
scorer.evaluate.pairing_contexts). On a two-stage split a chunk takes whole groups of the stage mapping (orig,
prev and every now2 and prev2): each token's comfort partner is then in its chunk; tokens no group covers are
scored too, after the groups. A chunk whose process died is planned again one token per chunk
(`split_chunk`), so that a token that kills its worker cannot take the others with it; its comfort partner
then comes as its context.

A log-replay split's tokens in that order are cut into blocks of PACK_TOKENS, whose metric caches the object
store keeps together as one pack (server.shared_caches: one GET for a block instead of one per token); chunks
are planned of whole blocks, so that they fetch whole packs. The blocks depend on the split alone (never on
the run's tokens still to score), so the packs one run publishes are those every later run reads.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.models import LIVE_CHUNK_STATES, ChunkState, ScoringChunk, Split, SplitKind, Submission, utc_now
from server.runs._finish import finish_if_complete
from server.runs._run import completed_tokens
from server.services.splits import scene_starts, split_tokens, stage_mapping

if TYPE_CHECKING:
    from scorer.two_stage.split import TwoStageSplit


PACK_TOKENS = 64  # a block's tokens: chunks of 384, 192 and 128 tokens (1, 2 and 3 seeds) are whole blocks
_BLOCKS_KEPT = 8  # splits whose blocks a worker process keeps (a navtest split's: ~1 MB)
_blocks_of_split: dict[str, Mapping[str, tuple[str, ...]]] = {}


@dataclass(frozen=True)
class Plan:
    """What planning a run did: chunks to send, or the run finished (every row was there), or dropped."""

    chunks: tuple[int, ...] = ()
    finished: bool = False
    dropped: bool = False


def plan_run(
    session: Session,
    submission_id: int,
    run: int,
    chunk_size: int,
    engine_version: str,
    bootstrap_samples: int,
) -> Plan:
    """Record the chunks of a claimed run's tokens without rows (the caller sends them), or finish the run
    when every row was written before an interruption."""
    submission = session.get(Submission, submission_id)
    done = completed_tokens(session, submission_id, run)
    if submission is None or done is None:
        return Plan(dropped=True)
    missing = [token for token in split_tokens(submission.split) if token not in done]
    if not missing:
        finish_if_complete(session, submission_id, run, engine_version, bootstrap_samples)
        return Plan(finished=True)
    # A chunk holds about chunk_size (token, seed) pairs, whatever the number of seeds.
    size = max(1, chunk_size // submission.seed_count)
    return Plan(chunks=tuple(plan_chunks(session, submission, missing, size)))


def _with_contexts(session: Session, submission: Submission, groups: list[list[str]]) -> list[ScoringChunk]:
    """Return queued chunks of the run for `groups` of tokens, each with the frames outside it that its tokens'
    two-frame comfort pairs them with."""
    # The engine is heavy: imported only where chunks are made.
    from scorer.evaluate import pairing_contexts
    from scorer.two_stage.score import comfort_pairs

    split = submission.split
    if split.kind == SplitKind.two_stage:
        partner = {a: b for pair in comfort_pairs(stage_mapping(split)) for a, b in (pair, pair[::-1])}
        contexts = [
            list(dict.fromkeys(partner[t] for t in group if t in partner and partner[t] not in group))
            for group in groups
        ]
    else:
        contexts = pairing_contexts(scene_starts(session, split), groups)
    return [
        ScoringChunk(submission_id=submission.id, run=submission.run, tokens=group, context=context)
        for group, context in zip(groups, contexts, strict=True)
    ]


def _whole_groups(stages: TwoStageSplit, tokens: Sequence[str], size: int) -> list[list[str]]:
    """Return `tokens` in chunks of about `size` that keep each group of the stage mapping whole (a larger group
    is a chunk of its own), in mapping order; then the tokens no group covers."""
    todo = set(tokens)
    groups = stages.groups or ()
    grouped = {token for group in groups for token in group.tokens}
    units = [[token for token in group.tokens if token in todo] for group in groups]
    units = [unit for unit in units if unit] + [[token] for token in tokens if token not in grouped]
    return _packed(units, size)


def _packed(units: Sequence[list[str]], size: int) -> list[list[str]]:
    """Return chunks of about `size` tokens, each of whole `units` (a larger unit is a chunk of its own)."""
    chunks: list[list[str]] = []
    for unit in units:
        if not chunks or len(chunks[-1]) + len(unit) > size:
            chunks.append([])
        chunks[-1] += unit
    return chunks


def log_order(tokens: Sequence[str], starts: Mapping[str, tuple[str, int]]) -> list[str]:
    """Return a log-replay split's `tokens` in log and time order (a scene that cannot be read first)."""
    return sorted(tokens, key=lambda token: (starts.get(token, ("", 0)), token))


def split_blocks(starts: Mapping[str, tuple[str, int]]) -> list[tuple[str, ...]]:
    """Return the blocks of a log-replay split whose readable scenes start at `starts` (`scene_starts`), in log
    order (a scene that cannot be read is in none: its token is read one by one)."""
    ordered = log_order(list(starts), starts)
    return [tuple(ordered[start : start + PACK_TOKENS]) for start in range(0, len(ordered), PACK_TOKENS)]


def token_blocks(session: Session, split: Split) -> Mapping[str, tuple[str, ...]]:
    """Return token -> its block for a log-replay split whose index of log frames planning built (none for a
    two-stage split, whose chunks keep groups whole instead), kept per split content: a worker reads the index
    once, not for every chunk, and never the object store (the index is in the database)."""
    blocks = _blocks_of_split.get(split.content_hash)
    if blocks is None:
        if split.kind == SplitKind.two_stage or split.scene_starts is None:
            return {}
        blocks = {token: block for block in split_blocks(scene_starts(session, split)) for token in block}
        if len(_blocks_of_split) >= _BLOCKS_KEPT:
            _blocks_of_split.pop(next(iter(_blocks_of_split)))
        _blocks_of_split[split.content_hash] = blocks
    return blocks


def plan_chunks(
    session: Session, submission: Submission, tokens: Sequence[str], size: int, now: datetime | None = None
) -> list[int]:
    """Record queued chunks of `size` for those of `tokens` no live chunk of the run holds; return their ids."""
    held = {
        token
        for chunk_tokens in session.scalars(
            select(ScoringChunk.tokens).where(
                ScoringChunk.submission_id == submission.id,
                ScoringChunk.run == submission.run,
                ScoringChunk.state.in_(LIVE_CHUNK_STATES),
            )
        )
        for token in chunk_tokens
    }
    todo = [token for token in tokens if token not in held]
    if submission.split.kind == SplitKind.two_stage:
        groups = _whole_groups(stage_mapping(submission.split), todo, size)
    else:  # whole blocks when a chunk holds one (the tokens of a block still to score, in log order)
        starts = scene_starts(session, submission.split)  # first: the blocks are cut from it
        blocks = token_blocks(session, submission.split)
        units: dict[object, list[str]] = {}
        for token in log_order(todo, starts):
            units.setdefault(blocks.get(token, token) if size >= PACK_TOKENS else token, []).append(token)
        groups = _packed(list(units.values()), size)
    chunks = _with_contexts(session, submission, groups)
    for chunk in chunks:
        chunk.sent_at = now or utc_now()
    session.add_all(chunks)
    session.flush()
    return [chunk.id for chunk in chunks]


def split_chunk(session: Session, chunk: ScoringChunk, now: datetime) -> tuple[int, ...]:
    """Plan a chunk's tokens again one per chunk, each inheriting its deaths; return the new chunks' ids."""
    submission = session.get(Submission, chunk.submission_id)
    assert submission is not None  # start_chunk checked the run
    children = _with_contexts(session, submission, [[token] for token in chunk.tokens])
    for child in children:
        child.deaths, child.sent_at = chunk.deaths, now
    session.add_all(children)
    chunk.state, chunk.finished_at = ChunkState.split_up, now
    session.flush()
    return tuple(child.id for child in children)
