"""jobs.source and jobs.delivery_*: jobs that name a DICOMweb series as input and store their DICOM
results back into the PACS by STOW-RS (issue 11)

`source` holds {"dicomweb": {"url", "study_uid", "series_uid"}} (never credentials: the PACS
Authorization header is a setting); `deliver_url` the STOW-RS base URL; `delivery_status`
(pending | delivered | failed), `delivery_attempts` and `delivery_error` the state of the delivery,
which is retried on its own, without refitting. Rows from before this revision are upload jobs: NULL
source and deliver_url, 0 attempts.

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("source", sa.JSON(), nullable=True))
        batch.add_column(sa.Column("deliver_url", sa.Text(), nullable=True))
        batch.add_column(sa.Column("delivery_status", sa.String(length=16), nullable=True))
        batch.add_column(sa.Column("delivery_attempts", sa.Integer(), nullable=False, server_default=sa.text("0")))
        batch.add_column(sa.Column("delivery_error", sa.Text(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        for name in ("delivery_error", "delivery_attempts", "delivery_status", "deliver_url", "source"):
            batch.drop_column(name)
