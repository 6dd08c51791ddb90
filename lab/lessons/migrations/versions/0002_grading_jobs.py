"""Grading jobs on Dask: when a running grading is given up, who graded it, how many results were stored.

Revision ID: 0002
Revises: 0001
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"


def upgrade() -> None:
    with op.batch_alter_table("lesson_submissions") as table:
        table.add_column(sa.Column("deadline", sa.Float(), nullable=True))
        table.add_column(sa.Column("worker", sa.String(200), nullable=True))
        table.add_column(sa.Column("gradings", sa.Integer(), nullable=False, server_default="0"))


def downgrade() -> None:
    with op.batch_alter_table("lesson_submissions") as table:
        table.drop_column("gradings")
        table.drop_column("worker")
        table.drop_column("deadline")
