"""The submissions database's schema under Alembic: :func:`upgrade` brings a database to :data:`HEAD` on open.

Revisions (``versions/``): ``0001`` is the schema the lab shipped before migrations (the tables
``lesson_submissions`` and ``lesson_assignments``); ``0002`` adds what grading jobs on Dask record
(``deadline``, ``worker``, ``gradings``). A database made before migrations existed (its tables,
no ``alembic_version``) is stamped ``0001`` first, then upgraded, so a course's rows are kept.

Several processes may open one database at once (a server, its Dask workers): the upgrade runs
in one transaction under the database's write lock (:func:`upgrade`), and within a process upgrades
take turns (Alembic loads env.py as a module of its own).
"""

from __future__ import annotations

import threading
from pathlib import Path

from sqlalchemy import inspect, text
from sqlalchemy.engine import Connection, Engine

#: The newest revision (``versions/``; a test checks Alembic's script directory agrees).
HEAD = "0002"
#: The revision of a database made before migrations (tables, no ``alembic_version``).
BASELINE = "0001"
#: The PostgreSQL advisory lock key the upgrade holds (any constant shared by every process of the lab).
ADVISORY_LOCK = 0x7615_1A8

FOLDER = Path(__file__).resolve().parent
#: Alembic loads env.py as a module of its own: one upgrade at a time in a process.
_upgrading = threading.Lock()


def alembic_config(connection: Connection | None = None):  # -> alembic.config.Config (imported lazily)
    """Alembic's configuration for these migrations, sharing ``connection`` with env.py."""
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(FOLDER))
    config.attributes["connection"] = connection
    return config


def current_revision(connection: Connection) -> str | None:
    """The revision stamped in ``alembic_version`` (None: not stamped, or no database yet)."""
    from alembic.runtime.migration import MigrationContext

    return MigrationContext.configure(connection).get_current_revision()


def upgrade(engine: Engine, revision: str = "head") -> None:
    """Bring the database to ``revision`` (default: the newest), stamping a pre-migration database
    :data:`BASELINE` first; nothing is done when it is already at :data:`HEAD`.

    The version is read and every migration runs in one transaction holding the database's write lock
    (PostgreSQL: an advisory lock; SQLite: ``BEGIN IMMEDIATE``, since its driver would otherwise commit
    each DDL statement on its own), so processes opening a database at once take turns.
    """
    with _upgrading, engine.connect() as connection:
        if connection.dialect.name != "sqlite":
            with connection.begin():
                if connection.dialect.name == "postgresql":
                    connection.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": ADVISORY_LOCK})
                _upgrade_locked(connection, revision)
            return
        driver = connection.connection.driver_connection
        previous = driver.isolation_level  # type: ignore[union-attr]
        driver.isolation_level = None  # type: ignore[union-attr]  # the transaction is ours, not the driver's
        try:
            connection.exec_driver_sql("BEGIN IMMEDIATE")
            _upgrade_locked(connection, revision)
            connection.commit()
        finally:
            if connection.in_transaction():
                connection.rollback()
            driver.isolation_level = previous  # type: ignore[union-attr]


def _upgrade_locked(connection: Connection, revision: str) -> None:
    from alembic import command

    current = current_revision(connection)
    if current == HEAD and revision in ("head", HEAD):
        return
    config = alembic_config(connection)
    if current is None and "lesson_submissions" in inspect(connection).get_table_names():
        command.stamp(config, BASELINE)
    command.upgrade(config, revision)


__all__ = ["BASELINE", "HEAD", "alembic_config", "current_revision", "upgrade"]
