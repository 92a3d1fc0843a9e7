"""SQL data model (SQLAlchemy 2): teams, tokens, splits, phases, submissions, results, audit log.

The submission row is the truth about a submission's state; the broker only carries work.
Enumerations are stored as short strings (not database enum types) so adding a value needs no
type migration.
"""

from __future__ import annotations

from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    UniqueConstraint,
    false,
    text,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator

# Stable constraint names, so migrations can drop and alter them on every backend.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utc_now() -> datetime:
    """Return the current time, timezone-aware in UTC."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """A timestamp that is always timezone-aware UTC in Python, on SQLite (naive storage) and PostgreSQL."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"naive datetime {value!r}: timestamps must carry a time zone")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    """Declarative base carrying the naming convention."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class Approval(StrEnum):
    pending = "pending"
    approved = "approved"
    rejected = "rejected"


class Scope(StrEnum):
    team = "team"
    admin = "admin"


class Status(StrEnum):
    queued = "queued"
    running = "running"
    scored = "scored"
    failed = "failed"
    cancelled = "cancelled"


ACTIVE_STATUSES = (Status.queued, Status.running)


class SplitKind(StrEnum):
    # What a split's directory holds decides how its runs are scored (server.runs.RUN_VERSIONS).
    log_replay = "log-replay"  # logged frames, other agents replaying the log (v1.0, v1.1, v2.2)
    two_stage = (
        "two-stage"  # a `two_stage.json` stage mapping: NAVSIM v2.2's two-stage EPDMS, reactive traffic
    )


class FailureKind(StrEnum):
    # Infrastructure failures (worker lost, timeouts, storage) are refunded; submission failures are not.
    infrastructure = "infrastructure"
    submission = "submission"


class Team(Base):
    __tablename__ = "teams"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    members: Mapped[list[str]] = mapped_column(JSON, default=list)
    affiliation: Mapped[str] = mapped_column(String(300), default="")
    approval: Mapped[str] = mapped_column(String(16), default=Approval.pending)
    # The team that owns the baseline submissions of every split; never holds tokens.
    is_system: Mapped[bool] = mapped_column(Boolean, default=False)
    # Written under the submission lock: the UPDATE that sets it serialises a team's uploads.
    last_submission_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)

    tokens: Mapped[list[ApiToken]] = relationship(back_populates="team")


class ApiToken(Base):
    __tablename__ = "api_tokens"

    id: Mapped[int] = mapped_column(primary_key=True)
    team_id: Mapped[int | None] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"), index=True)
    scope: Mapped[str] = mapped_column(String(16))
    name: Mapped[str] = mapped_column(String(200), default="")
    # sha256 of the secret: tokens are 256-bit random strings, so an unsalted hash cannot be inverted.
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(16))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    last_used_at: Mapped[datetime | None] = mapped_column(UTCDateTime)

    team: Mapped[Team | None] = relationship(back_populates="tokens")


class Split(Base):
    __tablename__ = "splits"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    directory: Mapped[str] = mapped_column(Text)
    content_hash: Mapped[str] = mapped_column(String(64))
    token_count: Mapped[int] = mapped_column(Integer)
    # Whether teams may see its scenes (maps, objects) in drill-down pictures; a hidden test split never.
    scenes_public: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    kind: Mapped[str] = mapped_column(
        String(16), default=SplitKind.log_replay, server_default=SplitKind.log_replay.value
    )
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    # token -> [log name, t0 in us] of its scenes, read once when a run is first planned on the split
    # (server.services.splits.scene_starts); large, so loaded only when asked for.
    scene_starts: Mapped[dict[str, list[Any]] | None] = mapped_column(JSON, deferred=True)

    subsets: Mapped[list[SplitSubset]] = relationship(back_populates="split", cascade="all, delete-orphan")


class SplitSubset(Base):
    """A named token subset of a split (e.g. public, private); "all" is implicit and never stored."""

    __tablename__ = "split_subsets"
    __table_args__ = (UniqueConstraint("split_id", "name"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    split_id: Mapped[int] = mapped_column(ForeignKey("splits.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(64))
    tokens: Mapped[list[str]] = mapped_column(JSON)

    split: Mapped[Split] = relationship(back_populates="subsets")


class Phase(Base):
    """A competition phase on one split, with its open window and default quotas (None: unlimited)."""

    __tablename__ = "phases"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    split_id: Mapped[int] = mapped_column(ForeignKey("splits.id"), index=True)
    opens_at: Mapped[datetime] = mapped_column(UTCDateTime)
    closes_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    per_day: Mapped[int | None] = mapped_column(Integer)
    total: Mapped[int | None] = mapped_column(Integer)
    in_flight: Mapped[int | None] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)

    split: Mapped[Split] = relationship()


class TeamQuota(Base):
    """A team's override of a phase's quotas; a None field keeps the phase default."""

    __tablename__ = "team_quotas"
    __table_args__ = (UniqueConstraint("team_id", "phase_id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id", ondelete="CASCADE"))
    phase_id: Mapped[int] = mapped_column(ForeignKey("phases.id", ondelete="CASCADE"))
    per_day: Mapped[int | None] = mapped_column(Integer)
    total: Mapped[int | None] = mapped_column(Integer)
    in_flight: Mapped[int | None] = mapped_column(Integer)


class Submission(Base):
    __tablename__ = "submissions"
    __table_args__ = (
        UniqueConstraint("team_id", "idempotency_key"),
        Index("ix_submissions_team_phase_status", "team_id", "phase_id", "status"),
        Index("ix_submissions_team_sha256", "team_id", "sha256"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id"))
    split_id: Mapped[int] = mapped_column(ForeignKey("splits.id"), index=True)
    # None for baselines, which belong to the split and appear in every phase on it.
    phase_id: Mapped[int | None] = mapped_column(ForeignKey("phases.id"), index=True)
    is_baseline: Mapped[bool] = mapped_column(Boolean, default=False)

    status: Mapped[str] = mapped_column(String(16), default=Status.queued, index=True)
    progress: Mapped[int] = mapped_column(Integer, default=0)
    # Incremented by every re-run; per-token rows of older runs are overwritten as the new run goes.
    run: Mapped[int] = mapped_column(Integer, default=1)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    error: Mapped[str | None] = mapped_column(Text)  # shown to the team: sanitised, never hidden-log content
    error_detail: Mapped[str | None] = mapped_column(Text)  # admins only
    failure_kind: Mapped[str | None] = mapped_column(String(16))
    # Whether the submission counts against the team's quotas (refunds clear it).
    charged: Mapped[bool] = mapped_column(Boolean, default=True)

    sha256: Mapped[str] = mapped_column(String(64))
    filename: Mapped[str] = mapped_column(String(300))
    stored_name: Mapped[str] = mapped_column(String(300))
    size_bytes: Mapped[int] = mapped_column(Integer)
    idempotency_key: Mapped[str | None] = mapped_column(String(200))

    method: Mapped[str] = mapped_column(String(300), default="")
    authors: Mapped[str] = mapped_column(Text, default="")
    email: Mapped[str] = mapped_column(String(300), default="")
    institution: Mapped[str] = mapped_column(String(300), default="")
    country: Mapped[str] = mapped_column(String(100), default="")
    tech_report_url: Mapped[str] = mapped_column(Text, default="")
    code_url: Mapped[str] = mapped_column(Text, default="")
    seed_count: Mapped[int] = mapped_column(Integer, default=1)
    token_count: Mapped[int] = mapped_column(Integer, default=0)

    hidden: Mapped[bool] = mapped_column(Boolean, default=False)
    admin_hidden: Mapped[bool] = mapped_column(Boolean, default=False)
    disqualified: Mapped[bool] = mapped_column(Boolean, default=False)
    disqualified_reason: Mapped[str] = mapped_column(Text, default="")
    selected: Mapped[bool] = mapped_column(Boolean, default=False)

    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    # When it last entered the queue (creation, re-run, requeue): a reaper re-sends what waits too long.
    queued_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    # When a worker last claimed the run and cut it into chunks (scoring_chunks say how they fare).
    claimed_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    worker: Mapped[str | None] = mapped_column(String(300))

    team: Mapped[Team] = relationship()
    split: Mapped[Split] = relationship()
    phase: Mapped[Phase | None] = relationship()


class ChunkState(StrEnum):
    queued = "queued"  # sent to the broker, not started
    running = "running"  # a worker process scores it and beats while it does
    done = "done"  # its rows are written
    split_up = "split"  # a worker died holding it: its tokens went out again one per chunk
    failed = "failed"  # one token whose own process died scoring it alone: written as failed rows


LIVE_CHUNK_STATES = (ChunkState.queued, ChunkState.running)
# Their rows are written: scored (done), or written as failed (a token that killed its process).
FINISHED_CHUNK_STATES = (ChunkState.done, ChunkState.failed)


class ScoringChunk(Base):
    """Some tokens of one run, scored by one task: the SQL record the reaper holds the broker to.

    A broker may lose a message (flushed, restarted) or hold it for a dead worker until its visibility
    timeout; the chunk's state, last send and the beat of the process scoring it say what to send again.
    """

    __tablename__ = "scoring_chunks"
    __table_args__ = (Index("ix_scoring_chunks_submission_run", "submission_id", "run"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"))
    run: Mapped[int] = mapped_column(Integer)
    tokens: Mapped[list[str]] = mapped_column(JSON)
    # Earlier frames of the tokens' logs that other chunks hold: scored too, for v2.2's two-frame comfort
    # to pair with, never written (scorer.evaluate.pairing_contexts).
    context: Mapped[list[str]] = mapped_column(JSON, default=list, server_default=text("'[]'"))
    state: Mapped[str] = mapped_column(String(16), default=ChunkState.queued, index=True)
    # Processes that died while scoring these tokens (inherited by the chunks of a split).
    deaths: Mapped[int] = mapped_column(Integer, default=0)
    starts: Mapped[int] = mapped_column(Integer, default=0)
    worker: Mapped[str | None] = mapped_column(String(300))  # the process scoring it: host/pid
    sent_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    beat_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class MetricColumns:
    """Every metric version's result columns (scorer.versions.ALL_RESULT_COLUMNS); a column a version lacks, or
    leaves undefined (v2.2's EC without an adjacent frame), is null."""

    no_at_fault_collisions: Mapped[float | None] = mapped_column(Float)
    drivable_area_compliance: Mapped[float | None] = mapped_column(Float)
    driving_direction_compliance: Mapped[float | None] = mapped_column(Float)
    traffic_light_compliance: Mapped[float | None] = mapped_column(Float)
    ego_progress: Mapped[float | None] = mapped_column(Float)
    time_to_collision_within_bound: Mapped[float | None] = mapped_column(Float)
    comfort: Mapped[float | None] = mapped_column(Float)
    lane_keeping: Mapped[float | None] = mapped_column(Float)
    history_comfort: Mapped[float | None] = mapped_column(Float)
    two_frame_extended_comfort: Mapped[float | None] = mapped_column(Float)
    score: Mapped[float | None] = mapped_column(Float)


class TokenResultRow(MetricColumns, Base):
    """One token's result under one metric version and seed; written idempotently per chunk."""

    __tablename__ = "token_results"
    __table_args__ = (
        UniqueConstraint("submission_id", "metric_version", "seed", "token"),
        # Which of a chunk's tokens are scored (server.runs._run.completed_tokens).
        Index("ix_token_results_submission_token", "submission_id", "token"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"))
    metric_version: Mapped[str] = mapped_column(String(16))
    seed: Mapped[int] = mapped_column(Integer)
    token: Mapped[str] = mapped_column(String(64))
    valid: Mapped[bool] = mapped_column(Boolean)
    error: Mapped[str | None] = mapped_column(Text)
    run: Mapped[int] = mapped_column(Integer)
    worker: Mapped[str] = mapped_column(String(300), default="")
    duration_s: Mapped[float] = mapped_column(Float, default=0.0)  # this token's share of its chunk's time
    scored_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    # How the row came about, as a team may read it (v2.2: the human filter's overrides, EC's partner).
    detail: Mapped[dict[str, Any] | None] = mapped_column(JSON)


class Result(MetricColumns, Base):
    """Means over one subset's tokens for one (submission, metric version, seed), with provenance."""

    __tablename__ = "results"
    __table_args__ = (UniqueConstraint("submission_id", "metric_version", "subset", "seed"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"), index=True)
    metric_version: Mapped[str] = mapped_column(String(16))
    subset: Mapped[str] = mapped_column(String(64))
    seed: Mapped[int] = mapped_column(Integer)
    tokens: Mapped[int] = mapped_column(Integer)
    failed: Mapped[int] = mapped_column(Integer)
    engine_version: Mapped[str] = mapped_column(String(64))
    split_hash: Mapped[str] = mapped_column(String(64))
    workers: Mapped[str] = mapped_column(Text, default="")
    duration_s: Mapped[float] = mapped_column(Float, default=0.0)
    # A two-stage run's seed (the metric columns hold its combined row): the stage-one and stage-two summary
    # rows, each group's parts, value and detail, each stage-two token's weight, the notes and `official`.
    two_stage: Mapped[dict[str, Any] | None] = mapped_column(JSON, deferred=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)


class Summary(MetricColumns, Base):
    """A leaderboard entry: the seeds of one (submission, metric version, subset) combined, with the CI.

    Metric columns hold means over seeds; `score_std`/`score_max` describe the spread of per-seed scores (PDMS or EPDMS),
    `ci_low`/`ci_high` the bootstrap 95% interval of the score over tokens (seed-averaged per token).
    """

    __tablename__ = "summaries"
    __table_args__ = (
        UniqueConstraint("submission_id", "metric_version", "subset"),
        Index("ix_summaries_version_subset", "metric_version", "subset"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"))
    metric_version: Mapped[str] = mapped_column(String(16))
    subset: Mapped[str] = mapped_column(String(64))
    seeds: Mapped[int] = mapped_column(Integer)
    score_std: Mapped[float] = mapped_column(Float)
    score_max: Mapped[float] = mapped_column(Float)
    ci_low: Mapped[float] = mapped_column(Float)
    ci_high: Mapped[float] = mapped_column(Float)
    tokens: Mapped[int] = mapped_column(Integer)
    failed: Mapped[int] = mapped_column(Integer)
    # A two-stage entry: the stage-one and stage-two summary rows (means over seeds), the groups scored and
    # those undefined; `ci_low`/`ci_high` are then over groups (their seed-averaged values).
    two_stage: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    computed_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)

    submission: Mapped[Submission] = relationship()


class AuditEntry(Base):
    """One admin action: who, what, on which object, with the details needed to understand it later."""

    __tablename__ = "audit_log"

    id: Mapped[int] = mapped_column(primary_key=True)
    at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now, index=True)
    actor: Mapped[str] = mapped_column(String(200))
    token_id: Mapped[int | None] = mapped_column(ForeignKey("api_tokens.id", ondelete="SET NULL"))
    action: Mapped[str] = mapped_column(String(64))
    target_type: Mapped[str] = mapped_column(String(32))
    target_id: Mapped[str] = mapped_column(String(64))
    details: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)


class Rescore(Base):
    """A rescore-all run: the leaderboard before it and the submissions it re-queued, for the rank report."""

    __tablename__ = "rescores"

    id: Mapped[int] = mapped_column(primary_key=True)
    metric_version: Mapped[str] = mapped_column(String(16))
    # The version of the ranking before (null in rescores made before it could differ: `metric_version`).
    before_version: Mapped[str | None] = mapped_column(String(16))
    subset: Mapped[str] = mapped_column(String(64))
    phase_id: Mapped[int] = mapped_column(ForeignKey("phases.id"))
    before: Mapped[list[dict[str, Any]]] = mapped_column(JSON)
    submission_ids: Mapped[list[int]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)


class WorkerHeartbeat(Base):
    """A worker's last sign of life, written every few seconds by the worker itself: the answer to "which
    workers run?" on transports that cannot broadcast a ping (the embedded broker)."""

    __tablename__ = "worker_heartbeats"

    name: Mapped[str] = mapped_column(String(255), primary_key=True)  # Celery node name, e.g. celery@host
    started_at: Mapped[datetime] = mapped_column(UTCDateTime)
    seen_at: Mapped[datetime] = mapped_column(UTCDateTime, index=True)


class IntegrityCheck(Base):
    """One run of the integrity checks over a split's entries, started by an organiser
    (`server.services.integrity`); its flags replace those of the split's previous check."""

    __tablename__ = "integrity_checks"

    id: Mapped[int] = mapped_column(primary_key=True)
    split_id: Mapped[int] = mapped_column(ForeignKey("splits.id"), index=True)
    started_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    entries: Mapped[int] = mapped_column(Integer, default=0)  # the submissions read
    skipped: Mapped[list[dict[str, Any]]] = mapped_column(JSON, default=list)  # unreadable ones, and why
    error: Mapped[str | None] = mapped_column(Text)

    split: Mapped[Split] = relationship()


class IntegrityFlag(Base):
    """A suspicion about a submission, with its evidence, for organisers only: it decides nothing by itself."""

    __tablename__ = "integrity_flags"

    id: Mapped[int] = mapped_column(primary_key=True)
    check_id: Mapped[int] = mapped_column(ForeignKey("integrity_checks.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(32))  # leaked_log, near_duplicate, probing
    submission_id: Mapped[int] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"), index=True)
    other_submission_id: Mapped[int | None] = mapped_column(ForeignKey("submissions.id", ondelete="CASCADE"))
    summary: Mapped[str] = mapped_column(Text)
    evidence: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)

    check: Mapped[IntegrityCheck] = relationship()
    submission: Mapped[Submission] = relationship(foreign_keys=[submission_id])
