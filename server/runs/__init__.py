"""A scoring run, from claim to leaderboard summaries: the one home of its lifecycle (the workers' Celery tasks
only carry it, worker.tasks).

A submission's run is claimed (`claim_submission`) and planned into chunks of consecutive frames
(`plan_run`), which travel as tasks while SQL records each. A chunk's walk, each module once:

    start_chunk (_chunks)  take the queued chunk (isolated after a death), or split it, or drop a duplicate
    chunk_inputs (_job)    the run's job and the chunk's tokens still without rows
    score_chunk (_score)   the engine, every seed and version at once (the caller beats meanwhile)
    write_chunk (_rows)    upsert the rows, finish the chunk's record, then (_finish) record the run's
                           progress and, after its last rows, aggregate it (_aggregate) and mark it scored

Once a run is scored and committed, its worker sends `check_integrity_after_run` (_after) as a task of its own,
which goes once behind the chunks waiting when it starts (`chunks_waiting`).
The reaper (`reap_dead_chunks`, `reap_lost_work`) decides from the same records what to send again and what
to fail; `mark_failed` fails a run with a message the team may read, refunding what was not its fault.
Admins `cancel` a run or start a new one (`reset_for_rerun`). Every write names its run (_run): a late chunk of
an older run is dropped, and a repeated one overwrites its rows.
"""

from server.runs._after import check_integrity_after_run, chunks_waiting
from server.runs._chunks import ChunkStart, StartAction, beat_chunk, start_chunk
from server.runs._finish import mark_scored
from server.runs._job import ChunkInputs, Rejected, ScoringJob, chunk_inputs
from server.runs._plan import Plan, plan_run, split_blocks
from server.runs._reaper import LOST_DEATHS, Reaped, reap_dead_chunks, reap_lost_work
from server.runs._rows import write_chunk, write_chunk_results
from server.runs._run import BOARD_VERSIONS, RUN_VERSIONS, run_versions
from server.runs._score import ScoredChunk, score_chunk
from server.runs._state import cancel, claim_submission, mark_failed, reset_for_rerun

__all__ = [
    "BOARD_VERSIONS",
    "LOST_DEATHS",
    "RUN_VERSIONS",
    "ChunkInputs",
    "ChunkStart",
    "Plan",
    "Reaped",
    "Rejected",
    "ScoredChunk",
    "ScoringJob",
    "StartAction",
    "beat_chunk",
    "cancel",
    "check_integrity_after_run",
    "chunk_inputs",
    "chunks_waiting",
    "claim_submission",
    "mark_failed",
    "mark_scored",
    "plan_run",
    "reap_dead_chunks",
    "reap_lost_work",
    "reset_for_rerun",
    "run_versions",
    "score_chunk",
    "split_blocks",
    "start_chunk",
    "write_chunk",
    "write_chunk_results",
]
