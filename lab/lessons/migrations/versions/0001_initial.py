"""The schema the lab shipped before migrations: submissions and assignment seeds.

Revision ID: 0001
Revises:
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None


def upgrade() -> None:
    op.create_table(
        "lesson_submissions",
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("lesson", sa.String(128), nullable=False),
        sa.Column("student", sa.String(200), nullable=False),
        sa.Column("filename", sa.String(255), nullable=False),
        sa.Column("source", sa.Text(), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("created", sa.Float(), nullable=False),
        sa.Column("started", sa.Float(), nullable=True),
        sa.Column("finished", sa.Float(), nullable=True),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("score", sa.Float(), nullable=True),
        sa.Column("max_score", sa.Float(), nullable=True),
        sa.Column("results", sa.Text(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
    )
    op.create_index("ix_lesson_submissions_lesson", "lesson_submissions", ["lesson"])
    op.create_index("ix_lesson_submissions_status", "lesson_submissions", ["status"])
    op.create_table(
        "lesson_assignments",
        sa.Column("lesson", sa.String(128), primary_key=True),
        sa.Column("seed", sa.Integer(), nullable=False),
        sa.Column("created", sa.Float(), nullable=False),
    )


def downgrade() -> None:
    op.drop_table("lesson_assignments")
    op.drop_index("ix_lesson_submissions_status", "lesson_submissions")
    op.drop_index("ix_lesson_submissions_lesson", "lesson_submissions")
    op.drop_table("lesson_submissions")
