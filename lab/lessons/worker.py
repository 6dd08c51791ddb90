"""A Dask worker with the lab's environment (``vision-lab worker``), and the set-up of embedded workers.

A grading worker is a plain ``distributed.Worker`` in a process where the lab is importable: before
it joins the scheduler it checks the bubblewrap sandbox (:func:`lab.lessons.isolation.check`; a
worker that could not grade refuses to start, naming the fix), limits the math libraries to one
thread each (a job's grading and its sandbox child share the worker's cores), and imports the
grader, so its first job does not pay for it. The database a job writes to and the lessons folder
come in the job (:class:`~lab.lessons.jobs.GradingJob`): the worker must reach both (the same
SQLite file on one machine; a PostgreSQL server and a shared lessons folder on a cluster).
"""

from __future__ import annotations

import asyncio
import importlib
import os
import signal
import tempfile
from typing import Any

from distributed import Worker, WorkerPlugin

#: Math-library thread counts a worker sets before anything imports them.
ONE_THREAD = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
              "NUMBA_NUM_THREADS")


class LabWorkerSetup(WorkerPlugin):
    """Applies the server's ``--unsafe-sandbox`` to the embedded cluster's worker processes."""

    name = "vision-lab-setup"

    def __init__(self, *, unsafe_sandbox: bool) -> None:
        self.unsafe_sandbox = unsafe_sandbox

    def setup(self, worker: Any) -> None:
        from lab.lessons.isolation import allow_unsafe

        allow_unsafe(self.unsafe_sandbox)


def prepare(*, unsafe_sandbox: bool = False) -> None:
    """The lab's environment for grading in this process; SandboxUnavailable when it could not grade."""
    for variable in ONE_THREAD:
        os.environ.setdefault(variable, "1")
    from lab.lessons import isolation

    isolation.allow_unsafe(unsafe_sandbox)
    isolation.check(isolation.default_isolation())
    importlib.import_module("lab.lessons.grader")  # the first job does not pay for the import


def run_worker(scheduler: str, *, nthreads: int = 1, name: str | None = None, host: str | None = None,
               unsafe_sandbox: bool = False) -> None:
    """Run a grading worker attached to ``scheduler`` until it is stopped (SIGINT, SIGTERM) or the
    scheduler closes it."""
    prepare(unsafe_sandbox=unsafe_sandbox)

    async def serve() -> None:
        with tempfile.TemporaryDirectory(prefix="vision-lab-worker-") as scratch:
            async with Worker(scheduler, nthreads=nthreads, name=name, host=host, dashboard=False,
                              local_directory=scratch, memory_limit=0) as worker:
                loop = asyncio.get_running_loop()
                for signum in (signal.SIGINT, signal.SIGTERM):
                    loop.add_signal_handler(signum, lambda: asyncio.ensure_future(worker.close()))
                await worker.finished()

    asyncio.run(serve())


__all__ = ["LabWorkerSetup", "prepare", "run_worker"]
