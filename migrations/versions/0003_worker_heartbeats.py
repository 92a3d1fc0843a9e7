"""Workers write heartbeats to the database (health and the admin console read them where no ping reaches).

Revision ID: 0003_worker_heartbeats
Revises: 0002_split_scenes_public
Create Date: 2026-11-24 21:55:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

import server.models

revision = "0003_worker_heartbeats"
down_revision = "0002_split_scenes_public"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "worker_heartbeats",
        sa.Column("name", sa.String(length=255), nullable=False),
        sa.Column("started_at", server.models.UTCDateTime(timezone=True), nullable=False),
        sa.Column("seen_at", server.models.UTCDateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("name", name=op.f("pk_worker_heartbeats")),
    )
    op.create_index(op.f("ix_worker_heartbeats_seen_at"), "worker_heartbeats", ["seen_at"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_worker_heartbeats_seen_at"), table_name="worker_heartbeats")
    op.drop_table("worker_heartbeats")
