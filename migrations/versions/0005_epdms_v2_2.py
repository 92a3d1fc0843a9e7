"""NAVSIM v2.2's EPDMS on the board: its result columns, each token's detail (the human filter's overrides, EC's
partner), the scenes' place in their logs, the earlier frames a chunk scores for EC to pair with, and the
version a rescore's report compares with.

Existing rows keep their values; their new columns are null (they were not scored under v2.2), and a split's
scene starts are read when a run is next planned on it.

Revision ID: 0005_epdms_v2_2
Revises: 0004_scoring_chunks
Create Date: 2026-11-25 07:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005_epdms_v2_2"
down_revision = "0004_scoring_chunks"
branch_labels = None
depends_on = None

RESULT_TABLES = ("token_results", "results", "summaries")
NEW_COLUMNS = ("traffic_light_compliance", "lane_keeping", "history_comfort", "two_frame_extended_comfort")


# Plain ALTER TABLE on both databases, as in 0002: SQLite's batch mode would copy referenced tables.
def upgrade() -> None:
    for table in RESULT_TABLES:
        for column in NEW_COLUMNS:
            op.add_column(table, sa.Column(column, sa.Float(), nullable=True))
    op.add_column("token_results", sa.Column("detail", sa.JSON(), nullable=True))
    op.add_column("splits", sa.Column("scene_starts", sa.JSON(), nullable=True))
    op.add_column(
        "scoring_chunks", sa.Column("context", sa.JSON(), server_default=sa.text("'[]'"), nullable=False)
    )
    op.add_column("rescores", sa.Column("before_version", sa.String(length=16), nullable=True))


def downgrade() -> None:
    op.drop_column("rescores", "before_version")
    op.drop_column("scoring_chunks", "context")
    op.drop_column("splits", "scene_starts")
    op.drop_column("token_results", "detail")
    for table in RESULT_TABLES:
        for column in NEW_COLUMNS:
            op.drop_column(table, column)
