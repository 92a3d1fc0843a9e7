"""NAVSIM v2.2's two-stage EPDMS on the board: a split's kind (a directory with `two_stage.json` is a two-stage
split, scored under `v2.2-two-stage`), and beside a two-stage run's results per seed and per entry the stage
summaries and groups that the combined score rests on.

Existing splits are log-replay splits (two-stage ones could not be registered before); existing results and
summaries have no two-stage part.

Revision ID: 0007_two_stage_splits
Revises: 0006_token_results_by_token
Create Date: 2026-11-28 03:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007_two_stage_splits"
down_revision = "0006_token_results_by_token"
branch_labels = None
depends_on = None


# Plain ALTER TABLE on both databases, as in 0002: SQLite's batch mode would copy referenced tables.
def upgrade() -> None:
    op.add_column(
        "splits", sa.Column("kind", sa.String(length=16), server_default="log-replay", nullable=False)
    )
    op.add_column("results", sa.Column("two_stage", sa.JSON(), nullable=True))
    op.add_column("summaries", sa.Column("two_stage", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("summaries", "two_stage")
    op.drop_column("results", "two_stage")
    op.drop_column("splits", "kind")
