"""Where grading runs: a Dask cluster (embedded by default, or an existing scheduler) fed from the database.

:class:`GradingCluster` is the Dask client: a ``LocalCluster`` started in the server's own process
(threads, no set-up: the default) or an existing scheduler named by ``VISION_LAB_DASK_SCHEDULER=
tcp://host:port`` whose workers are ``vision-lab worker`` processes (or dask-jobqueue's, or a
Kubernetes deployment's, each with the lab installed).

:class:`Dispatcher` is one thread of the server: it claims queued submissions from the database
while the cluster has room (one per worker thread, so a job starts when it is claimed and its
deadline is a bound on grading, not on waiting in a queue), submits each claim as a job
(:func:`lab.lessons.jobs.run_job`, Dask key ``grade-<id>-<attempt>``), and watches them:

- a job's own result is written by the job (the database is the one source of truth);
- a worker lost mid-job is retried by Dask on another worker (the scheduler's
  ``allowed-failures``); a job that killed that many workers is marked ``error``;
- a job lost with the scheduler (the future cancelled) goes back to ``queued`` (:meth:`release`);
- a running submission past its deadline (``2 × total_timeout_s + 60 s`` by default,
  ``VISION_LAB_GRADING_DEADLINE_S``) is marked ``error`` with a message and its job cancelled.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from lab.lessons.jobs import GradingJob, JobOutcome, forget, local_grader, run_job
from lab.lessons.store import GradeFunction, Submission, SubmissionQueue

log = logging.getLogger("lab.lessons")

#: The environment variable naming an existing scheduler (``tcp://host:port``).
SCHEDULER_VARIABLE = "VISION_LAB_DASK_SCHEDULER"


class GradingCluster:
    """A Dask client on the cluster that runs grading jobs (started lazily, by :meth:`start`).

    ``scheduler``: an existing scheduler's address; else an embedded ``LocalCluster`` of
    ``workers`` workers of one thread each, threads of this process (``processes=False``: starts in
    about half a second and adds ~7 MiB) or worker processes (``processes=True``: ~6 s and ~75 MiB
    per worker before a lesson is imported, but no shared GIL with the server).
    """

    def __init__(self, *, scheduler: str | None = None, workers: int = 1, processes: bool = False) -> None:
        if workers < 1:
            raise ValueError("a grading cluster needs at least one worker")
        self.scheduler = scheduler or None
        self.workers = int(workers)
        self.processes = bool(processes)
        self.client: Any = None  # distributed.Client once started
        self._local: Any = None

    @property
    def in_process(self) -> bool:
        """Jobs run in this process (the embedded threads cluster): they may use its objects."""
        return self.scheduler is None and not self.processes

    def start(self) -> None:
        if self.client is not None:
            return
        from distributed import Client, LocalCluster

        if self.scheduler is not None:
            self.client = Client(self.scheduler, timeout="30s", set_as_default=False)
            return
        # the scheduler's and workers' HTTP endpoints exist even without a dashboard: loopback only, any port
        self._local = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=self.processes,
                                   dashboard_address="127.0.0.1:0", worker_dashboard_address="127.0.0.1:0",
                                   host="127.0.0.1" if self.processes else None)
        self.client = Client(self._local, set_as_default=False)
        if self.processes:
            from lab.lessons.isolation import unsafe_allowed
            from lab.lessons.worker import LabWorkerSetup

            self.client.register_plugin(LabWorkerSetup(unsafe_sandbox=unsafe_allowed()))

    def capacity(self) -> int:
        """Jobs the cluster runs at once now: its workers' threads (0 before it starts or with no worker)."""
        if self.client is None:
            return 0
        try:
            return int(sum(self.client.nthreads().values()))
        except Exception:  # the scheduler is unreachable for the moment
            return 0

    def submit(self, job: GradingJob, grade: GradeFunction | str | None) -> Any:
        return self.client.submit(run_job, job, grade, key=job.key, retries=1)

    def close(self) -> None:
        client, local = self.client, self._local
        self.client = self._local = None
        if client is not None:
            client.close(timeout=5)
        if local is not None:
            local.close(timeout=5)


@dataclass
class _InFlight:
    submission_id: str
    attempt: int
    future: Any


class Dispatcher:
    """Feeds the cluster from the database's queue (see the module docstring); one thread."""

    def __init__(self, queue: SubmissionQueue, cluster: GradingCluster, *,
                 job_of: Callable[[Submission], GradingJob], grade: GradeFunction | None = None,
                 deadline_s: Callable[[str], float] | None = None, poll_s: float = 1.0) -> None:
        self.queue = queue
        self.cluster = cluster
        self.job_of = job_of
        self.grade = grade
        self.deadline_s = deadline_s
        self.poll_s = poll_s
        self._token: str | None = None
        self._in_flight: dict[str, _InFlight] = {}
        self._stop = threading.Event()
        self._wake = threading.Condition()
        self._threads: list[threading.Thread] = []  # the one dispatching thread, while running

    @property
    def running(self) -> bool:
        return bool(self._threads)

    @property
    def busy(self) -> int:
        """Jobs submitted and not yet reaped."""
        return len(self._in_flight)

    def start(self) -> None:
        if self._threads:
            return
        self.cluster.start()
        if self.grade is not None and self.cluster.in_process:
            self._token = local_grader(self.grade)
        self._stop.clear()
        thread = threading.Thread(target=self._loop, name="grading-dispatcher", daemon=True)
        thread.start()
        self._threads = [thread]

    def wake(self) -> None:
        with self._wake:
            self._wake.notify_all()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop claiming; jobs still running finish on their workers (their results are stored). With the
        embedded threads cluster, a running grading gets ``timeout`` seconds to finish before the cluster
        closes; what is left is requeued at the next start."""
        self._stop.set()
        self.wake()
        for thread in self._threads:
            thread.join(timeout=timeout)
        self._threads = []
        pending = [entry.future for entry in self._in_flight.values()]
        if pending and self.cluster.in_process:  # this process's gradings: let them finish, as before
            end = time.monotonic() + timeout
            while any(not future.done() for future in pending) and time.monotonic() < end:
                time.sleep(0.05)
            left = sum(not future.done() for future in pending)
            if left:
                log.warning("stopping with %d grading(s) running: requeued at the next start", left)
        self._in_flight.clear()
        self.cluster.close()
        if self._token is not None:
            forget(self._token)
            self._token = None

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.step()
            except Exception:  # the database or the scheduler is unreachable for a moment: try again later
                log.exception("dispatching grading jobs failed")
            with self._wake:
                self._wake.wait(timeout=self.poll_s)

    def step(self) -> int:
        """One round: reap finished jobs, give up overdue ones, claim and submit while there is room;
        returns how many jobs were submitted."""
        self._reap()
        for submission_id, attempt in self.queue.fail_overdue():
            entry = self._in_flight.pop(f"grade-{submission_id}-{attempt}", None)
            if entry is not None:
                entry.future.cancel()
        submitted = 0
        while len(self._in_flight) < self.cluster.capacity() and not self._stop.is_set():
            claimed = self.queue.claim(deadline_s=self.deadline_s)
            if claimed is None:
                break
            job = self.job_of(claimed)
            future = self.cluster.submit(job, self._token if self._token is not None else self.grade)
            future.add_done_callback(lambda _future: self.wake())
            self._in_flight[job.key] = _InFlight(claimed.id, claimed.attempts, future)
            submitted += 1
        return submitted

    def _reap(self) -> None:
        for key, entry in list(self._in_flight.items()):
            if not entry.future.done():
                continue
            del self._in_flight[key]
            self._settle(entry)

    def _settle(self, entry: _InFlight) -> None:
        """A finished future: the job stored its result itself; what is left is a job that did not run to
        its end."""
        from distributed import KilledWorker

        if entry.future.cancelled():
            if self.queue.release(entry.submission_id, entry.attempt):
                log.warning("the job of submission %s was lost with the scheduler: requeued",
                            entry.submission_id)
            return
        error = entry.future.exception()
        if error is None:
            outcome: JobOutcome = entry.future.result()
            log.debug("submission %s: %s on %s", outcome.submission_id, outcome.status, outcome.worker)
            return
        if isinstance(error, KilledWorker):
            self.queue.fail(entry.submission_id, "every grading worker that took this submission died while "
                                                 "grading it; ask your instructor", attempt=entry.attempt)
            return
        log.warning("the job of submission %s failed (%s: %s): requeued", entry.submission_id,
                    type(error).__name__, error)
        self.queue.release(entry.submission_id, entry.attempt)


__all__ = ["SCHEDULER_VARIABLE", "Dispatcher", "GradingCluster"]
