"""Scoring chunks in SQL (the reaper re-sends what a broker lost or a dead worker held); a run's claim time
replaces its lease.

Revision ID: 0004_scoring_chunks
Revises: 0003_worker_heartbeats
Create Date: 2026-11-24 23:20:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

import server.models

revision = "0004_scoring_chunks"
down_revision = "0003_worker_heartbeats"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "scoring_chunks",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("submission_id", sa.Integer(), nullable=False),
        sa.Column("run", sa.Integer(), nullable=False),
        sa.Column("tokens", sa.JSON(), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("deaths", sa.Integer(), nullable=False),
        sa.Column("starts", sa.Integer(), nullable=False),
        sa.Column("worker", sa.String(length=300), nullable=True),
        sa.Column("sent_at", server.models.UTCDateTime(timezone=True), nullable=False),
        sa.Column("started_at", server.models.UTCDateTime(timezone=True), nullable=True),
        sa.Column("beat_at", server.models.UTCDateTime(timezone=True), nullable=True),
        sa.Column("finished_at", server.models.UTCDateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(
            ["submission_id"],
            ["submissions.id"],
            name=op.f("fk_scoring_chunks_submission_id_submissions"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_scoring_chunks")),
    )
    op.create_index("ix_scoring_chunks_submission_run", "scoring_chunks", ["submission_id", "run"])
    op.create_index(op.f("ix_scoring_chunks_state"), "scoring_chunks", ["state"], unique=False)
    # A run in flight during the upgrade has no chunks: the reaper re-plans it once its old lease has run out.
    with op.batch_alter_table("submissions") as batch:
        batch.alter_column("lease_expires_at", new_column_name="claimed_at")


def downgrade() -> None:
    with op.batch_alter_table("submissions") as batch:
        batch.alter_column("claimed_at", new_column_name="lease_expires_at")
    op.drop_index(op.f("ix_scoring_chunks_state"), table_name="scoring_chunks")
    op.drop_index("ix_scoring_chunks_submission_run", table_name="scoring_chunks")
    op.drop_table("scoring_chunks")
