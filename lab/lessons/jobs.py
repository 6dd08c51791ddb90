"""A grading job: what runs on the Dask worker that takes it, and writes its result into the database.

A job (:class:`GradingJob`) names a claimed submission (its id and the claim's attempt number), its
lesson, the assignment seed every hidden dataset is derived from, and where the database and the
lessons are. :func:`run_job` reads the submission's source from the database, grades it in the
bubblewrap sandbox (:func:`lab.lessons.grader.grade`, exactly as a grading in the server did) and
stores results.json with a conditional write (:meth:`~lab.lessons.store.SubmissionQueue.finish`):
the row must still be ``running`` under the same attempt, so however many times Dask ran the job
(a worker lost mid-job is retried elsewhere) the submission is graded once in the database. A
bug of the lab or the lesson in grading marks the submission ``error`` with the reason, as before.

Workers open the database and the lesson catalog once per process (:func:`queue_for`,
:func:`catalog_for`). In the server's own process (the embedded threads cluster) the job uses the
server's objects, registered by :func:`register`, and an injected grade function (tests) stays in
the process: it is passed by a token (:func:`local_grader`), not pickled.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import uuid
from dataclasses import dataclass

from lab.lessons.format import LessonCatalog
from lab.lessons.store import GradeFunction, Submission, SubmissionQueue

log = logging.getLogger("lab.lessons")


@dataclass(frozen=True)
class GradingJob:
    """One grading of one claimed submission (what crosses to the worker: names and a seed, no code)."""

    database_url: str
    lessons_dir: str
    submission_id: str
    lesson: str
    attempt: int
    seed: int

    @property
    def key(self) -> str:
        """The Dask key: one per claim, so a job submitted twice for the same claim runs as one task."""
        return f"grade-{self.submission_id}-{self.attempt}"


@dataclass(frozen=True)
class JobOutcome:
    """What a run of a job did: ``stored`` whether this run wrote the submission's result (``done`` or
    ``error``); ``gone`` when the claim no longer held (graded already, requeued, given up)."""

    submission_id: str
    attempt: int
    status: str  # "done" | "error" | "gone"
    stored: bool
    worker: str


_lock = threading.Lock()
_queues: dict[str, SubmissionQueue] = {}
_catalogs: dict[str, LessonCatalog] = {}
_graders: dict[str, GradeFunction] = {}


def register(queue: SubmissionQueue, catalog: LessonCatalog) -> None:
    """Jobs run in this process use ``queue`` and ``catalog`` for their URL and folder (the server's own)."""
    with _lock:
        _queues[queue.url] = queue
        _catalogs[str(catalog.root)] = catalog


def queue_for(url: str) -> SubmissionQueue:
    """This process's queue on database ``url`` (opened, and upgraded, once)."""
    with _lock:
        if url not in _queues:
            _queues[url] = SubmissionQueue(url)
        return _queues[url]


def catalog_for(folder: str) -> LessonCatalog:
    """This process's catalog of the lessons in ``folder`` (each lesson loaded once)."""
    with _lock:
        if folder not in _catalogs:
            _catalogs[folder] = LessonCatalog(folder)
        return _catalogs[folder]


def local_grader(grade: GradeFunction) -> str:
    """A token standing for ``grade`` in jobs run in this process (registered until :func:`forget`)."""
    token = uuid.uuid4().hex
    with _lock:
        _graders[token] = grade
    return token


def forget(token: str) -> None:
    with _lock:
        _graders.pop(token, None)


def worker_name() -> str:
    """The Dask worker running this job (its name), else this host and process."""
    try:
        from distributed import get_worker

        return str(get_worker().name)
    except (ImportError, ValueError):  # not on a Dask worker (a direct call)
        return f"{socket.gethostname()}:{os.getpid()}"


def default_grade(job: GradingJob, submission: Submission) -> dict:
    """The grader, in the sandbox, on the lesson's hidden data derived from the job's seed."""
    from lab.lessons.grader import grade

    lesson = catalog_for(job.lessons_dir).get(job.lesson)
    return grade(lesson, submission.source, seed=job.seed).results_json()


def run_job(job: GradingJob, grade: GradeFunction | str | None = None) -> JobOutcome:
    """Grade the job's submission and store the result once (see the module docstring).

    ``grade``: None for the grader; a token of :func:`local_grader`; or a function (pickled to the
    worker). Only a failure to reach the database escapes (Dask then retries the job).
    """
    queue = queue_for(job.database_url)
    name = worker_name()
    if not queue.mark_started(job.submission_id, job.attempt, name):
        return JobOutcome(job.submission_id, job.attempt, "gone", False, name)
    submission = queue.get(job.submission_id)
    assert submission is not None  # claimed rows are never deleted
    function = _graders.get(grade) if isinstance(grade, str) else grade
    if isinstance(grade, str) and function is None:
        raise LookupError(f"grade function {grade!r} is not registered in this process")
    try:
        results = function(submission) if function is not None else default_grade(job, submission)
    except Exception as exc:
        log.exception("grading submission %s failed", job.submission_id)
        stored = queue.fail(job.submission_id, f"grading failed ({type(exc).__name__}: {exc}); this is a "
                                               "problem of the lab, not of your code", attempt=job.attempt)
        return JobOutcome(job.submission_id, job.attempt, "error" if stored else "gone", stored, name)
    stored = queue.finish(job.submission_id, results, attempt=job.attempt, worker=name)
    if not stored:
        log.info("submission %s attempt %d was graded already or given up: result not stored",
                 job.submission_id, job.attempt)
    return JobOutcome(job.submission_id, job.attempt, "done" if stored else "gone", stored, name)


__all__ = ["GradingJob", "JobOutcome", "catalog_for", "local_grader", "queue_for", "register", "run_job"]
