"""Submissions that survive the server: a SQLAlchemy table used as a persistent queue.

A submission is written (committed) before its id is returned, with status ``queued``. The grading
dispatcher (:mod:`lab.lessons.cluster`) claims the oldest queued submissions with a conditional
UPDATE (``queued`` -> ``running``, ``attempts`` + 1: one claimer wins, on SQLite and PostgreSQL
alike) and hands each to a Dask worker as a job (:mod:`lab.lessons.jobs`), which stores Gradescope's
results.json with status ``done``. The table is the one source of truth, and a result is stored
*exactly once*: :meth:`SubmissionQueue.finish` and :meth:`~SubmissionQueue.fail` write only while the
row is still ``running`` under the claim's attempt number, so a job Dask ran twice (a worker lost
mid-job, a result that came after its deadline, a job of a server that was restarted meanwhile)
cannot overwrite or double a grade (``gradings`` counts the results stored). A claim carries a
deadline: a running submission past it is marked ``error`` (:meth:`~SubmissionQueue.fail_overdue`).

When the server starts, whatever is still ``running`` was interrupted (the server was killed mid-
grading) and goes back to ``queued``; a submission interrupted :data:`MAX_ATTEMPTS` times is
marked ``error`` instead, so one that crashes the grader cannot loop forever.

The database is SQLite (a file in the user's data folder) by default and any SQLAlchemy URL through
``VISION_LAB_DATABASE_URL`` (``postgresql+psycopg://user:pass@host/course`` for a real course). Its
schema is kept by Alembic (:mod:`lab.lessons.migrations`): opening a database upgrades it, keeping its
rows. One server process owns a database's queue: requeueing at start-up assumes no other live
server is dispatching from the same database (workers writing results are fine: their claims are
void once requeued).

The same database keeps each lesson's *assignment seed* (table ``lesson_assignments``): the secret
from which the grader derives every hidden dataset of a grading run, drawn once per lesson
(:meth:`SubmissionQueue.assignment_seed`) or set by the instructor, so a regrade of the same file
gives the same score. It is never part of a submission's JSON.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

from sqlalchemy import (ColumnElement, Float, Integer, String, Text, create_engine, event, insert, select,
                        update)
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import CursorResult, Engine, Result
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column

from lab.core.errors import InvalidValue

log = logging.getLogger("lab.lessons")

#: Times a submission may be interrupted mid-grading before it is given up (status "error").
MAX_ATTEMPTS = 3

STATUSES = ("queued", "running", "done", "error")

#: The largest assignment seed: 31 bits, so it fits a signed 32-bit INTEGER column on every database.
MAX_SEED = 2**31 - 1

#: Statuses a regrade puts back in the queue (``error`` too: it was the lab's fault, maybe fixed since).
REGRADED = ("done", "error")


def _rowcount(result: Result[Any]) -> int:
    """The rows an UPDATE matched: a session's UPDATE without RETURNING gives a CursorResult, which its
    type does not say (sqlalchemy/sqlalchemy#12913)."""
    return cast("CursorResult[Any]", result).rowcount


class Base(DeclarativeBase):
    pass


class SubmissionRow(Base):
    """One uploaded file and, once graded, its results.json."""

    __tablename__ = "lesson_submissions"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    lesson: Mapped[str] = mapped_column(String(128), index=True)
    student: Mapped[str] = mapped_column(String(200), default="")
    filename: Mapped[str] = mapped_column(String(255))
    source: Mapped[str] = mapped_column(Text)
    status: Mapped[str] = mapped_column(String(16), index=True)
    created: Mapped[float] = mapped_column(Float)
    started: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished: Mapped[float | None] = mapped_column(Float, nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    score: Mapped[float | None] = mapped_column(Float, nullable=True)
    max_score: Mapped[float | None] = mapped_column(Float, nullable=True)
    results: Mapped[str | None] = mapped_column(Text, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    # revision 0002: grading jobs
    deadline: Mapped[float | None] = mapped_column(Float, nullable=True)
    worker: Mapped[str | None] = mapped_column(String(200), nullable=True)
    gradings: Mapped[int] = mapped_column(Integer, default=0, server_default="0")


class AssignmentRow(Base):
    """A lesson's assignment seed: drawn on first use or set by the instructor, never shown to students."""

    __tablename__ = "lesson_assignments"

    lesson: Mapped[str] = mapped_column(String(128), primary_key=True)
    seed: Mapped[int] = mapped_column(Integer)
    created: Mapped[float] = mapped_column(Float)


def check_seed(value: object, *, field: str = "seed") -> int:
    """``value`` as an assignment seed (an integer in 0 .. 2**31 - 1), else :class:`InvalidValue`."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidValue(field, f"an assignment seed is an integer, not {type(value).__name__}")
    if not 0 <= value <= MAX_SEED:
        raise InvalidValue(field, f"an assignment seed is between 0 and {MAX_SEED} (31 bits), not {value}")
    return int(value)


@dataclass(frozen=True)
class Submission:
    """A submission as read from the database (detached from any session)."""

    id: str
    lesson: str
    student: str
    filename: str
    source: str
    status: str
    created: float
    started: float | None
    finished: float | None
    attempts: int
    score: float | None
    max_score: float | None
    results: dict[str, Any] | None
    error: str | None
    deadline: float | None = None
    worker: str | None = None
    gradings: int = 0

    @classmethod
    def of(cls, row: SubmissionRow) -> Submission:
        return cls(id=row.id, lesson=row.lesson, student=row.student, filename=row.filename,
                   source=row.source, status=row.status, created=row.created, started=row.started,
                   finished=row.finished,
                   attempts=row.attempts, score=row.score, max_score=row.max_score,
                   results=json.loads(row.results) if row.results else None, error=row.error,
                   deadline=row.deadline, worker=row.worker, gradings=row.gradings or 0)

    def to_json(self, *, with_results: bool = True) -> dict[str, Any]:
        out: dict[str, Any] = {"id": self.id, "lesson": self.lesson, "student": self.student,
                               "filename": self.filename, "status": self.status, "created": self.created,
                               "started": self.started, "finished": self.finished, "attempts": self.attempts,
                               "score": self.score, "max_score": self.max_score, "error": self.error,
                               "worker": self.worker, "gradings": self.gradings}
        if with_results:
            out["results"] = self.results
        return out


def default_database_url() -> str:
    """``$VISION_LAB_DATABASE_URL``, else the SQLite file ``$XDG_DATA_HOME/vision-lab/submissions.sqlite``
    (``~/.local/share/vision-lab/submissions.sqlite``)."""
    configured = os.environ.get("VISION_LAB_DATABASE_URL")
    if configured:
        return configured
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return "sqlite:///" + os.path.join(base, "vision-lab", "submissions.sqlite")


def make_engine(url: str) -> Engine:
    """An engine for ``url``; SQLite gets a busy timeout and write-ahead logging for concurrent workers."""
    if url.startswith("sqlite"):
        from sqlalchemy.engine import make_url

        database = make_url(url).database
        if database and database != ":memory:" and not database.startswith("file:"):
            os.makedirs(os.path.dirname(os.path.abspath(database)), exist_ok=True)
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(connection, _record) -> None:  # pragma: no cover - exercised through SQLite
            cursor = connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA busy_timeout=30000")
            cursor.close()

        return engine
    return create_engine(url, pool_pre_ping=True)


class SubmissionQueue:
    """The submissions table as a queue: submit, claim, finish or fail, requeue after a crash."""

    def __init__(self, url: str | None = None, *, engine: Engine | None = None) -> None:
        self.url = url or default_database_url()
        self.engine = engine or make_engine(self.url)
        from lab.lessons.migrations import upgrade

        upgrade(self.engine)

    def submit(self, lesson: str, filename: str, source: str, *, student: str = "") -> str:
        """Store a new submission (committed before this returns); returns its id."""
        submission_id = uuid.uuid4().hex
        with Session(self.engine) as session, session.begin():
            session.add(SubmissionRow(id=submission_id, lesson=lesson, student=student, filename=filename,
                                      source=source, status="queued", created=time.time(), attempts=0))
        return submission_id

    def claim(self, *, deadline_s: Callable[[str], float] | None = None) -> Submission | None:
        """Mark the oldest queued submission ``running`` (its ``attempts`` + 1) and return it (None when
        the queue is empty). ``deadline_s(lesson)``: seconds from now after which the grading is given up
        (:meth:`fail_overdue`); None: no deadline."""
        for _ in range(10):  # another claimer may win the race for a row: try the next one
            with Session(self.engine) as session, session.begin():
                row = session.execute(select(SubmissionRow.id, SubmissionRow.lesson)
                                      .where(SubmissionRow.status == "queued")
                                      .order_by(SubmissionRow.created, SubmissionRow.id).limit(1)).first()
                if row is None:
                    return None
                row_id, lesson = row
                now = time.time()
                deadline = None if deadline_s is None else now + float(deadline_s(lesson))
                claimed = session.execute(
                    update(SubmissionRow).where(SubmissionRow.id == row_id, SubmissionRow.status == "queued")
                    .values(status="running", started=now, attempts=SubmissionRow.attempts + 1,
                            deadline=deadline, worker=None))
                if _rowcount(claimed) == 1:
                    found = session.get(SubmissionRow, row_id)
                    assert found is not None  # this transaction has just claimed it
                    return Submission.of(found)
        return None

    def _claimed(self, submission_id: str, attempt: int | None) -> ColumnElement[bool]:
        """The row while it is still under the claim ``attempt`` (any claim when None)."""
        condition = (SubmissionRow.id == submission_id) & (SubmissionRow.status == "running")
        return condition if attempt is None else condition & (SubmissionRow.attempts == attempt)

    def _write(self, submission_id: str, attempt: int | None, **values: Any) -> bool:
        with Session(self.engine) as session, session.begin():
            written = session.execute(update(SubmissionRow).where(self._claimed(submission_id, attempt))
                                      .values(**values))
        return _rowcount(written) == 1

    def mark_started(self, submission_id: str, attempt: int | None, worker: str) -> bool:
        """A job began on ``worker`` (recorded while the claim holds); whether the claim still holds."""
        return self._write(submission_id, attempt, worker=worker[:200])

    def finish(self, submission_id: str, results: dict[str, Any], *, attempt: int | None = None,
               worker: str | None = None) -> bool:
        """Store results.json (status ``done``) if the submission is still ``running`` under claim
        ``attempt``; whether it was stored. A second result for the same claim is refused, so a job
        that ran twice is stored once."""
        values: dict[str, Any] = {
            "status": "done", "finished": time.time(), "results": json.dumps(results),
            "score": float(results.get("score", 0.0)), "error": None, "gradings": SubmissionRow.gradings + 1,
            "max_score": float(sum(t.get("max_score", 0.0) for t in results.get("tests", [])))}
        if worker is not None:
            values["worker"] = worker[:200]
        return self._write(submission_id, attempt, **values)

    def fail(self, submission_id: str, error: str, *, attempt: int | None = None) -> bool:
        """Grading itself failed (a bug in the lab or the lesson, a lost job, never the student's code):
        status ``error`` if the claim ``attempt`` still holds; whether it was written."""
        return self._write(submission_id, attempt, status="error", finished=time.time(), error=error[:4000])

    def release(self, submission_id: str, attempt: int) -> bool:
        """A job lost with its scheduler: back to ``queued`` (to be claimed again) if the claim holds, or
        ``error`` after :data:`MAX_ATTEMPTS` claims."""
        if attempt >= MAX_ATTEMPTS:
            return self.fail(submission_id, f"grading was interrupted {MAX_ATTEMPTS} times; ask your "
                                            "instructor", attempt=attempt)
        return self._write(submission_id, attempt, status="queued", started=None, deadline=None)

    def fail_overdue(self, now: float | None = None) -> list[tuple[str, int]]:
        """Mark every ``running`` submission past its deadline ``error`` (no result came in time); the
        (id, attempt) of each."""
        now = time.time() if now is None else now
        with Session(self.engine) as session:
            overdue = session.execute(select(SubmissionRow.id, SubmissionRow.attempts, SubmissionRow.deadline,
                                             SubmissionRow.started)
                                      .where(SubmissionRow.status == "running",
                                             SubmissionRow.deadline.is_not(None),
                                             SubmissionRow.deadline < now)).all()
        given_up = []
        for row_id, attempt, deadline, started in overdue:
            waited = (deadline - started) if started is not None and deadline is not None else 0.0
            if self.fail(row_id, f"no result came within {waited:.0f} s of the grading starting (a grading "
                                 "worker was lost or overloaded); submit again or ask your instructor",
                         attempt=attempt):
                given_up.append((row_id, int(attempt)))
        if given_up:
            log.warning("gave up on %d submission(s) past their deadline", len(given_up))
        return given_up

    def requeue_running(self) -> int:
        """At start-up: submissions left ``running`` by a killed server go back to ``queued`` (or
        ``error``)."""
        with Session(self.engine) as session, session.begin():
            gave_up = _rowcount(session.execute(
                update(SubmissionRow).where(SubmissionRow.status == "running",
                                            SubmissionRow.attempts >= MAX_ATTEMPTS)
                .values(status="error", finished=time.time(),
                        error=f"grading was interrupted {MAX_ATTEMPTS} times; ask your instructor")))
            requeued = _rowcount(session.execute(
                update(SubmissionRow).where(SubmissionRow.status == "running")
                .values(status="queued", started=None, deadline=None)))
        if requeued or gave_up:
            log.warning("requeued %d interrupted submission(s), gave up on %d", requeued, gave_up)
        return int(requeued)

    def requeue_lesson(self, lesson: str) -> int:
        """A regrade: every ``done`` (or ``error``) submission of ``lesson`` goes back to ``queued``; returns
        how many. Their previous results stay until the new ones replace them (:meth:`finish`), so a
        regrade that is interrupted loses no grade; a submission ``running`` now is not touched."""
        with Session(self.engine) as session, session.begin():
            requeued = _rowcount(session.execute(
                update(SubmissionRow)
                .where(SubmissionRow.lesson == lesson, SubmissionRow.status.in_(REGRADED))
                .values(status="queued", started=None, attempts=0)))
        if requeued:
            log.info("regrading %d submission(s) of %s", requeued, lesson)
        return int(requeued)

    # --- assignment seeds ------------------------------------------------------------------------------
    def assignment_seed(self, lesson: str) -> int:
        """The lesson's assignment seed, drawn with :mod:`secrets` on first use. Race-safe: two workers
        (or servers) asking at once both insert-or-ignore, then read the one row that won."""
        seed = self._stored_seed(lesson)
        if seed is None:
            self._insert_seed(lesson, secrets.randbits(31))
            seed = self._stored_seed(lesson)
            assert seed is not None  # inserted by this call or by the one that won the race
        return seed

    def set_assignment_seed(self, lesson: str, seed: int) -> int:
        """Store ``seed`` (checked by :func:`check_seed`) as the lesson's assignment seed; returns it.
        Submissions graded from now on use it; regrade the lesson (:meth:`requeue_lesson`) for the others."""
        seed = check_seed(seed)
        with Session(self.engine) as session, session.begin():
            changed = session.execute(update(AssignmentRow).where(AssignmentRow.lesson == lesson)
                                      .values(seed=seed, created=time.time()))
        if _rowcount(changed) == 0 and not self._insert_seed(lesson, seed):
            with Session(self.engine) as session, session.begin():  # inserted by another call meanwhile
                session.execute(update(AssignmentRow).where(AssignmentRow.lesson == lesson).values(seed=seed))
        return seed

    def _stored_seed(self, lesson: str) -> int | None:
        with Session(self.engine) as session:
            seed = session.execute(select(AssignmentRow.seed).where(AssignmentRow.lesson == lesson)).scalar()
        return None if seed is None else int(seed)

    def _insert_seed(self, lesson: str, seed: int) -> bool:
        """INSERT the row unless one exists (``ON CONFLICT DO NOTHING`` on SQLite and PostgreSQL, a caught
        IntegrityError elsewhere); whether this call inserted it."""
        values = {"lesson": lesson, "seed": int(seed), "created": time.time()}
        dialect = self.engine.dialect.name
        if dialect in ("sqlite", "postgresql"):
            statement = (sqlite.insert(AssignmentRow).values(**values).on_conflict_do_nothing(
                index_elements=["lesson"]) if dialect == "sqlite" else postgresql.insert(AssignmentRow)
                .values(**values).on_conflict_do_nothing(index_elements=["lesson"]))
            with Session(self.engine) as session, session.begin():
                return _rowcount(session.execute(statement)) == 1
        try:
            with Session(self.engine) as session, session.begin():
                session.execute(insert(AssignmentRow).values(**values))
        except IntegrityError:
            return False
        return True

    def get(self, submission_id: str) -> Submission | None:
        with Session(self.engine) as session:
            row = session.get(SubmissionRow, submission_id)
            return Submission.of(row) if row is not None else None

    def list(self, lesson: str | None = None, *, limit: int | None = 1000) -> list[Submission]:
        """Submissions, newest first (``limit=None``: all of them)."""
        with Session(self.engine) as session:
            query = select(SubmissionRow).order_by(SubmissionRow.created.desc()).limit(limit)
            if lesson is not None:
                query = query.where(SubmissionRow.lesson == lesson)
            return [Submission.of(row) for row in session.execute(query).scalars()]

    def counts(self, lesson: str | None = None) -> dict[str, int]:
        """Submissions per status (of one lesson, or all)."""
        query = select(SubmissionRow.status)
        if lesson is not None:
            query = query.where(SubmissionRow.lesson == lesson)
        with Session(self.engine) as session:
            rows = session.execute(query).scalars().all()
        return {status: sum(1 for r in rows if r == status) for status in STATUSES}

    def close(self) -> None:
        self.engine.dispose()


#: What grades a claimed submission: its results.json (tests inject one; the default runs the grader).
GradeFunction = Callable[[Submission], dict[str, Any]]
