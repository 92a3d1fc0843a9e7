"""Integrity checks for organisers: each run of the checks over a split, and the flags it raised with their
evidence (a leaked log, near-identical entries of different teams, a team probing the hidden set).

Revision ID: 0008_integrity_checks
Revises: 0007_two_stage_splits
Create Date: 2026-11-28 03:20:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

import server.models

revision = "0008_integrity_checks"
down_revision = "0007_two_stage_splits"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "integrity_checks",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("split_id", sa.Integer(), nullable=False),
        sa.Column("started_at", server.models.UTCDateTime(timezone=True), nullable=False),
        sa.Column("finished_at", server.models.UTCDateTime(timezone=True), nullable=True),
        sa.Column("entries", sa.Integer(), nullable=False),
        sa.Column("skipped", sa.JSON(), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.ForeignKeyConstraint(
            ["split_id"], ["splits.id"], name=op.f("fk_integrity_checks_split_id_splits")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_integrity_checks")),
    )
    op.create_index(op.f("ix_integrity_checks_split_id"), "integrity_checks", ["split_id"], unique=False)
    op.create_table(
        "integrity_flags",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("check_id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=32), nullable=False),
        sa.Column("submission_id", sa.Integer(), nullable=False),
        sa.Column("other_submission_id", sa.Integer(), nullable=True),
        sa.Column("summary", sa.Text(), nullable=False),
        sa.Column("evidence", sa.JSON(), nullable=False),
        sa.ForeignKeyConstraint(
            ["check_id"],
            ["integrity_checks.id"],
            name=op.f("fk_integrity_flags_check_id_integrity_checks"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["submission_id"],
            ["submissions.id"],
            name=op.f("fk_integrity_flags_submission_id_submissions"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["other_submission_id"],
            ["submissions.id"],
            name=op.f("fk_integrity_flags_other_submission_id_submissions"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_integrity_flags")),
    )
    op.create_index(op.f("ix_integrity_flags_check_id"), "integrity_flags", ["check_id"], unique=False)
    op.create_index(
        op.f("ix_integrity_flags_submission_id"), "integrity_flags", ["submission_id"], unique=False
    )


def downgrade() -> None:
    op.drop_index(op.f("ix_integrity_flags_submission_id"), table_name="integrity_flags")
    op.drop_index(op.f("ix_integrity_flags_check_id"), table_name="integrity_flags")
    op.drop_table("integrity_flags")
    op.drop_index(op.f("ix_integrity_checks_split_id"), table_name="integrity_checks")
    op.drop_table("integrity_checks")
