"""Alembic's environment: migrations run on the connection :func:`lab.lessons.migrations.upgrade` gives."""

from __future__ import annotations

from alembic import context

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError("run the lab's migrations through lab.lessons.migrations.upgrade(engine)")
context.configure(connection=connection, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
