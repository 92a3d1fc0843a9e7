"""An index of per-token rows by (submission, token): a chunk asks which of its own tokens are scored, in a run
of about 100,000 rows, and is answered from those tokens' rows alone (the unique key leads with the metric
version and seed, which the question does not name).

Revision ID: 0006_token_results_by_token
Revises: 0005_epdms_v2_2
Create Date: 2026-11-25 09:00:00
"""

from __future__ import annotations

from alembic import op

revision = "0006_token_results_by_token"
down_revision = "0005_epdms_v2_2"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("ix_token_results_submission_token", "token_results", ["submission_id", "token"])


def downgrade() -> None:
    op.drop_index("ix_token_results_submission_token", table_name="token_results")
