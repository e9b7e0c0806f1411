"""jobs.artifacts_ref: which attempt's published outputs a succeeded job serves

Each attempt publishes its outputs under its own key (app/storage.py) and the job row names the
winner in the same compare-and-swap UPDATE that marks it succeeded, so a late or duplicate attempt
can never replace or half-delete the artifacts of a finished job. Rows from before this revision keep
NULL, which means the old single directory jobs/<id>/artifacts/.

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("artifacts_ref", sa.String(length=64), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("artifacts_ref")
