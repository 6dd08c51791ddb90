"""Submissions that survive the server: a SQLAlchemy table used as a persistent queue, and the worker pool.

A submission is written (committed) before its id is returned, with status ``queued``. Workers
claim the oldest queued submission with a conditional UPDATE (``queued`` -> ``running``: one
worker wins, on SQLite and PostgreSQL alike), grade it in a worker thread (the student's code runs
in the sandbox's child process) and store Gradescope's results.json with status ``done``. When
the server starts, whatever is still ``running`` was interrupted (the server was killed mid-
grading) and goes back to ``queued``; a submission interrupted :data:`MAX_ATTEMPTS` times is
marked ``error`` instead, so one that crashes the grader cannot loop forever.

The database is SQLite (a file in the user's data folder) by default and any SQLAlchemy URL through
``VISION_LAB_DATABASE_URL`` (``postgresql+psycopg://user:pass@host/course`` for a real course).
One server process owns a database's queue: requeueing at start-up assumes no other live
process is grading from the same database.

The same database keeps each lesson's *assignment seed* (table ``lesson_assignments``): the secret
from which the grader derives every hidden dataset of a grading run, drawn once per lesson
(:meth:`SubmissionQueue.assignment_seed`) or set by the instructor, so a regrade of the same file
gives the same score. It is never part of a submission's JSON.
"""

from __future__ import annotations

import logging
import os
import secrets
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

from sqlalchemy import Float, Integer, String, Text, create_engine, event, insert, select, update
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

    @classmethod
    def of(cls, row: SubmissionRow) -> Submission:
        import json

        return cls(id=row.id, lesson=row.lesson, student=row.student, filename=row.filename,
                   source=row.source, status=row.status, created=row.created, started=row.started,
                   finished=row.finished,
                   attempts=row.attempts, score=row.score, max_score=row.max_score,
                   results=json.loads(row.results) if row.results else None, error=row.error)

    def to_json(self, *, with_results: bool = True) -> dict[str, Any]:
        out: dict[str, Any] = {"id": self.id, "lesson": self.lesson, "student": self.student,
                               "filename": self.filename, "status": self.status, "created": self.created,
                               "started": self.started, "finished": self.finished, "attempts": self.attempts,
                               "score": self.score, "max_score": self.max_score, "error": self.error}
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
        Base.metadata.create_all(self.engine)

    def submit(self, lesson: str, filename: str, source: str, *, student: str = "") -> str:
        """Store a new submission (committed before this returns); returns its id."""
        submission_id = uuid.uuid4().hex
        with Session(self.engine) as session, session.begin():
            session.add(SubmissionRow(id=submission_id, lesson=lesson, student=student, filename=filename,
                                      source=source, status="queued", created=time.time(), attempts=0))
        return submission_id

    def claim(self) -> Submission | None:
        """Mark the oldest queued submission ``running`` and return it (None when the queue is empty)."""
        for _ in range(10):  # another worker may win the race for a row: try the next one
            with Session(self.engine) as session, session.begin():
                row_id = session.execute(select(SubmissionRow.id).where(SubmissionRow.status == "queued")
                                         .order_by(SubmissionRow.created, SubmissionRow.id).limit(1)).scalar()
                if row_id is None:
                    return None
                claimed = session.execute(
                    update(SubmissionRow).where(SubmissionRow.id == row_id, SubmissionRow.status == "queued")
                    .values(status="running", started=time.time(), attempts=SubmissionRow.attempts + 1))
                if _rowcount(claimed) == 1:
                    row = session.get(SubmissionRow, row_id)
                    assert row is not None  # this transaction has just claimed it
                    return Submission.of(row)
        return None

    def finish(self, submission_id: str, results: dict[str, Any]) -> None:
        import json

        with Session(self.engine) as session, session.begin():
            session.execute(update(SubmissionRow).where(SubmissionRow.id == submission_id).values(
                status="done", finished=time.time(), results=json.dumps(results),
                score=float(results.get("score", 0.0)),
                max_score=float(sum(t.get("max_score", 0.0) for t in results.get("tests", []))), error=None))

    def fail(self, submission_id: str, error: str) -> None:
        """Grading itself failed (a bug in the lab or the lesson, never the student's code)."""
        with Session(self.engine) as session, session.begin():
            session.execute(update(SubmissionRow).where(SubmissionRow.id == submission_id).values(
                status="error", finished=time.time(), error=error[:4000]))

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
                .values(status="queued", started=None)))
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


GradeFunction = Callable[[Submission], dict[str, Any]]


class WorkerPool:
    """Threads that take submissions off the queue and grade them, never in a request.

    ``grade`` maps a claimed submission to its results.json; an exception there (a bug in the lab
    or the lesson) marks the submission ``error`` with the reason. :meth:`wake` is called after a
    submit so a worker starts at once; workers also poll every ``poll_s`` seconds (other
    processes may write to the same database).
    """

    def __init__(self, queue: SubmissionQueue, grade: GradeFunction, *, workers: int = 1,
                 poll_s: float = 1.0) -> None:
        if workers < 1:
            raise ValueError("a worker pool needs at least one worker")
        self.queue = queue
        self.grade = grade
        self.workers = workers
        self.poll_s = poll_s
        self._stop = threading.Event()
        self._wake = threading.Condition()
        self._threads: list[threading.Thread] = []
        self.busy = 0

    def start(self) -> None:
        if self._threads:
            return
        self._stop.clear()
        for index in range(self.workers):
            thread = threading.Thread(target=self._loop, name=f"grader-{index}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def wake(self) -> None:
        with self._wake:
            self._wake.notify_all()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop taking work; a grading in progress finishes (or is requeued at the next start)."""
        self._stop.set()
        self.wake()
        for thread in self._threads:
            thread.join(timeout=timeout)
        self._threads = []

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                job = self.queue.claim()
            except Exception:  # the database is unreachable for a moment: try again later
                log.exception("claiming a submission failed")
                job = None
            if job is None:
                with self._wake:
                    self._wake.wait(timeout=self.poll_s)
                continue
            self.busy += 1
            try:
                results = self.grade(job)
            except Exception as exc:
                log.exception("grading submission %s failed", job.id)
                self.queue.fail(job.id, f"grading failed ({type(exc).__name__}: {exc}); this is a problem of "
                                        "the lab, not of your code")
            else:
                self.queue.finish(job.id, results)
            finally:
                self.busy -= 1
