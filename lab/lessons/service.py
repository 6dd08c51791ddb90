"""What the REST API's lesson routes run on: the lesson catalog, the submission queue and the grading cluster.

:func:`LessonService.from_env` reads the configuration from the environment:

``VISION_LAB_DATABASE_URL``
    SQLAlchemy URL of the submissions database (default: the SQLite file
    ``~/.local/share/vision-lab/submissions.sqlite``).
``VISION_LAB_LESSONS_DIR``
    Folder of lessons (default: ``lessons/`` beside the ``lab`` package).
``VISION_LAB_DASK_SCHEDULER``
    ``tcp://host:port`` of an existing Dask scheduler whose workers (``vision-lab worker``) grade;
    unset: an embedded ``LocalCluster`` in this process (:mod:`lab.lessons.cluster`).
``VISION_LAB_GRADING_WORKERS``
    Workers of the embedded cluster (default 1; each grading uses one sandbox process).
``VISION_LAB_DASK_PROCESSES``
    ``1``: the embedded cluster's workers are processes rather than threads of the server.
``VISION_LAB_GRADING_DEADLINE_S``
    Seconds after its claim a grading with no result is marked ``error`` (default: twice the
    lesson's ``total_timeout_s`` plus 60 s).
``VISION_LAB_INSTRUCTOR_TOKEN``
    When set, the instructor's routes (a lesson's submissions, its assignment seed, a regrade, the
    class's stats, a submission's instructor view) need ``Authorization: Bearer <token>``.
``VISION_LAB_MAX_SUBMISSION_BYTES``
    Largest accepted upload (default 256 KiB).

Every submission is graded with its lesson's assignment seed (kept in the submissions database,
:meth:`~lab.lessons.store.SubmissionQueue.assignment_seed`), so a regrade of the same file gives the
same score; :meth:`LessonService.regrade` requeues a lesson's graded submissions after the seed or
the lesson changed.
"""

from __future__ import annotations

import contextlib
import logging
import os

from lab.core.errors import LabError
from lab.lessons import isolation
from lab.lessons.cluster import SCHEDULER_VARIABLE, Dispatcher, GradingCluster
from lab.lessons.format import LessonCatalog, Limits
from lab.lessons.jobs import GradingJob, register
from lab.lessons.sandbox import remove_stale_workdirs
from lab.lessons.stats import ClassStats, class_stats, latest_per_student
from lab.lessons.store import GradeFunction, Submission, SubmissionQueue

DEFAULT_MAX_SUBMISSION_BYTES = 256 * 1024
#: A grading's deadline after its claim: ``DEADLINE_FACTOR × total_timeout_s + DEADLINE_MARGIN_S`` (one
#: retry on another worker after a lost one, and the worker's start-up).
DEADLINE_FACTOR = 2.0
DEADLINE_MARGIN_S = 60.0

log = logging.getLogger("lab.lessons")


class LessonService:
    """Lessons, their submissions and the graders; started and stopped with the server."""

    def __init__(self, *, catalog: LessonCatalog | None = None, queue: SubmissionQueue | None = None,
                 workers: int = 1, grade: GradeFunction | None = None, instructor_token: str | None = None,
                 max_submission_bytes: int = DEFAULT_MAX_SUBMISSION_BYTES, poll_s: float = 1.0,
                 cluster: GradingCluster | None = None, deadline_s: float | None = None) -> None:
        self.catalog = catalog or LessonCatalog()
        self.queue = queue or SubmissionQueue()
        self.instructor_token = instructor_token or None
        self.max_submission_bytes = int(max_submission_bytes)
        self.cluster = cluster or GradingCluster(workers=workers)
        self.deadline = deadline_s
        self.pool = Dispatcher(self.queue, self.cluster, job_of=self.job_of, grade=grade,
                               deadline_s=self.deadline_s, poll_s=poll_s)
        self.started = False
        self.needs_sandbox = grade is None  # an injected grade function (tests) runs no student code
        self.sandbox_problem: str | None = None

    @classmethod
    def from_env(cls, environ: dict[str, str] | None = None) -> LessonService:
        environ = dict(os.environ if environ is None else environ)
        lessons_dir = environ.get("VISION_LAB_LESSONS_DIR")
        return cls(catalog=LessonCatalog(lessons_dir) if lessons_dir else LessonCatalog(),
                   queue=SubmissionQueue(environ.get("VISION_LAB_DATABASE_URL") or None),
                   cluster=GradingCluster(scheduler=environ.get(SCHEDULER_VARIABLE) or None,
                                          workers=int(environ.get("VISION_LAB_GRADING_WORKERS", "1")),
                                          processes=environ.get("VISION_LAB_DASK_PROCESSES", "") == "1"),
                   deadline_s=(float(environ["VISION_LAB_GRADING_DEADLINE_S"])
                               if environ.get("VISION_LAB_GRADING_DEADLINE_S") else None),
                   instructor_token=environ.get("VISION_LAB_INSTRUCTOR_TOKEN"),
                   max_submission_bytes=int(environ.get("VISION_LAB_MAX_SUBMISSION_BYTES",
                                                        DEFAULT_MAX_SUBMISSION_BYTES)))

    def job_of(self, submission: Submission) -> GradingJob:
        """The job grading a claimed submission: where it is, its claim and the lesson's assignment seed."""
        return GradingJob(database_url=self.queue.url, lessons_dir=str(self.catalog.root),
                          submission_id=submission.id, lesson=submission.lesson, attempt=submission.attempts,
                          seed=self.queue.assignment_seed(submission.lesson))

    def deadline_s(self, lesson: str) -> float:
        """Seconds from its claim after which a grading of ``lesson`` with no result is given up."""
        if self.deadline is not None:
            return self.deadline
        limits = Limits()  # an injected grade function (tests) grades no lesson: the lesson is not loaded
        if self.needs_sandbox:
            with contextlib.suppress(LabError):  # a lesson that does not load: its job fails fast, saying why
                limits = self.catalog.get(lesson).limits
        return DEADLINE_FACTOR * limits.total_timeout_s + DEADLINE_MARGIN_S

    def start(self, *, dispatch: bool = True) -> int:
        """Remove what a crash left in the temporary folder, requeue what a killed server left running, check
        the sandbox (when grading runs in this process; a ``vision-lab worker`` checks its own) and start
        the grading cluster and its dispatcher; returns how many were requeued.

        Without a working sandbox (:func:`lab.lessons.isolation.check`) no worker starts: queued
        submissions stay queued (nothing is lost or scored 0) and :meth:`submit` answers
        :class:`~lab.lessons.isolation.SandboxUnavailable` (HTTP 503) naming the fix.

        ``dispatch=False`` (an API worker that leaves grading to another process on the same database,
        ``vision-lab serve --no-grading``): only the sandbox check, so :meth:`submit` refuses exactly
        where the grading process would; nothing is requeued, removed or claimed.
        """
        if self.started:
            return 0
        if not dispatch:
            self._check_sandbox()
            self.started = True
            return 0
        removed = remove_stale_workdirs()
        if removed:
            log.info("removed %d submission folders left by a crash", removed)
        requeued = self.queue.requeue_running()
        register(self.queue, self.catalog)  # jobs run in this process use the server's own objects
        self._check_sandbox()
        if self.sandbox_problem is None:
            self.pool.start()
        self.started = True
        return requeued

    def _check_sandbox(self) -> None:
        """Probe the sandbox when grading runs on this machine (a problem: :attr:`sandbox_problem`)."""
        if self.needs_sandbox and self.cluster.scheduler is None:
            try:
                isolation.check(isolation.default_isolation())
            except isolation.SandboxUnavailable as exc:
                self.sandbox_problem = exc.reason
                log.warning("grading is off: %s", exc.reason)

    def stop(self) -> None:
        self.pool.stop()
        self.started = False

    def submit(self, lesson: str, filename: str, source: str, *, student: str = "") -> str:
        if self.sandbox_problem is not None:
            raise isolation.SandboxUnavailable(self.sandbox_problem)
        submission_id = self.queue.submit(lesson, filename, source, student=student)
        self.pool.wake()
        return submission_id

    def regrade(self, lesson: str) -> int:
        """Requeue every graded (``done`` or ``error``) submission of the lesson, to be graded again with
        its current assignment seed; returns how many. Their results stay until the new ones land."""
        requeued = self.queue.requeue_lesson(lesson)
        self.pool.wake()
        return requeued

    def stats(self, lesson: str) -> ClassStats:
        """The class's view of a lesson: the latest graded submission of each student
        (:mod:`lab.lessons.stats`)."""
        return class_stats(latest_per_student(self.queue.list(lesson, limit=None)), lesson=lesson)
