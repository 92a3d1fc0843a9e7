"""Splits say whether teams may see their scenes in drill-down pictures (hidden unless an organiser says so).

Revision ID: 0002_split_scenes_public
Revises: 0001_initial
Create Date: 2026-11-24 21:35:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002_split_scenes_public"
down_revision = "0001_initial"
branch_labels = None
depends_on = None


# Plain ALTER TABLE on both databases: SQLite's batch mode would copy the table, and dropping the old copy
# fails while phases and submissions reference it.
def upgrade() -> None:
    op.add_column(
        "splits", sa.Column("scenes_public", sa.Boolean(), server_default=sa.false(), nullable=False)
    )


def downgrade() -> None:
    op.drop_column("splits", "scenes_public")
