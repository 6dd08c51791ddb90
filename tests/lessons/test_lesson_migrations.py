"""The submissions database under Alembic: opening a database upgrades it and keeps a course's rows."""

from __future__ import annotations

import multiprocessing
import threading

from sqlalchemy import create_engine, text

from lab.lessons import migrations
from lab.lessons.store import Base, SubmissionQueue, make_engine
from postgres_server import database_url  # noqa: F401  (a fixture: SQLite, then PostgreSQL)

OLD_ROW = {"id": "a" * 32, "lesson": "00-toy", "student": "ana", "filename": "a.py", "source": "x = 1",
           "status": "done", "created": 1.0, "started": 2.0, "finished": 3.0, "attempts": 1, "score": 4.0,
           "max_score": 6.0, "results": '{"score": 4.0, "tests": []}', "error": None}


def _at_previous_revision(url: str, *, stamped: bool = True) -> None:
    """A database as revision 0001 left it, with a graded submission and a seed (``stamped=False``: as the
    lab made it before migrations existed, with no alembic_version table)."""
    engine = make_engine(url)
    migrations.upgrade(engine, migrations.BASELINE)
    with engine.begin() as connection:
        connection.execute(text("INSERT INTO lesson_submissions VALUES (:id, :lesson, :student, :filename, "
                                ":source, :status, :created, :started, :finished, :attempts, :score, "
                                ":max_score, :results, :error)"), OLD_ROW)
        connection.execute(text("INSERT INTO lesson_assignments VALUES ('00-toy', 4711, 1.0)"))
        if not stamped:
            connection.execute(text("DROP TABLE alembic_version"))
    engine.dispose()


def _revision(url: str) -> str | None:
    engine = create_engine(url)
    with engine.connect() as connection:
        revision = migrations.current_revision(connection)
    engine.dispose()
    return revision


def test_the_head_constant_is_alembics_head():
    from alembic.script import ScriptDirectory

    assert ScriptDirectory.from_config(migrations.alembic_config()).get_current_head() == migrations.HEAD


def test_migrations_make_the_schema_the_model_describes(database_url):  # noqa: F811
    from alembic.autogenerate import compare_metadata
    from alembic.runtime.migration import MigrationContext

    queue = SubmissionQueue(database_url)
    with queue.engine.connect() as connection:
        assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
    queue.close()


def test_a_database_at_the_previous_revision_is_upgraded_keeping_its_rows(database_url):  # noqa: F811
    _at_previous_revision(database_url)
    assert _revision(database_url) == "0001"
    queue = SubmissionQueue(database_url)
    assert _revision(database_url) == migrations.HEAD
    kept = queue.get(OLD_ROW["id"])
    assert (kept.student, kept.score, kept.results, kept.attempts) == ("ana", 4.0, {"score": 4.0, "tests": []}, 1)
    assert (kept.gradings, kept.worker, kept.deadline) == (0, None, None)
    assert queue.assignment_seed("00-toy") == 4711
    new = queue.submit("00-toy", "b.py", "x = 2")  # and the upgraded table takes new rows and claims
    assert queue.claim(deadline_s=lambda lesson: 60.0).id == new
    queue.close()


def test_a_database_made_before_migrations_is_stamped_then_upgraded(database_url):  # noqa: F811
    _at_previous_revision(database_url, stamped=False)
    assert _revision(database_url) is None
    queue = SubmissionQueue(database_url)
    assert _revision(database_url) == migrations.HEAD and queue.get(OLD_ROW["id"]).score == 4.0
    queue.close()


def _open_and_close(url: str) -> None:
    SubmissionQueue(url).close()


def test_processes_opening_a_new_database_at_once_all_get_the_schema(database_url):  # noqa: F811
    processes = [multiprocessing.get_context("fork").Process(target=_open_and_close, args=(database_url,))
                 for _ in range(4)]
    for process in processes:
        process.start()
    for process in processes:
        process.join(timeout=60)
    assert [p.exitcode for p in processes] == [0] * 4 and _revision(database_url) == migrations.HEAD


def test_threads_opening_a_new_database_at_once_all_get_the_schema(database_url):  # noqa: F811
    errors: list[BaseException] = []

    def open_it():
        try:
            SubmissionQueue(database_url).close()
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=open_it) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == [] and _revision(database_url) == migrations.HEAD
