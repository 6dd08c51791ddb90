"""Running steps for the API: bounded worker pools, checks before a run, the job, progress for event
streams.

A step runs through :meth:`Session.run` on a thread of one of the app's bounded :class:`RunPools`
(never in the event loop), so ``/api/health`` stays fast, and the viewer, which shares the
session, sees the same state, history and lock. A step whose last run in the session was quick
goes to the light pool, so it does not wait behind other users' heavy steps, dataset loads go to
a pool of their own (a flood of creations cannot hold up steps), the rest to the heavy pool.
When a pool's workers are busy a run waits in its bounded queue; when the queue is full too, it
is refused with 429 and Retry-After.

Each session gets one :class:`RunMonitor` (kept beside the session, not in it) that records the
progress snapshots and the final outcome of the latest run, whoever started it, for
``GET /api/sessions/{id}/events``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import os
import sys
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from queue import Empty, SimpleQueue
from typing import Any, TypeVar

from lab.api.errors import error_body, jsonable, log
from lab.core.errors import Cancelled, InvalidControl, LabError, MissingInput, SessionBusy, TooManyRequests
from lab.core.pipeline import Plan, RunRecord, Session
from lab.core.step import Progress, StepSpec
from lab.core.store import SessionStore

#: Progress snapshots kept per run for subscribers who connect late (older ones are dropped).
MAX_EVENTS = 1000
#: A run started outside the API (the viewer) is seen through its progress; if it ends without a
#: history record (a bug), subscribers get an error after this long.
ORPHAN_SECONDS = 2.0
#: Worker threads of the default pool: the CPUs, at least 2 and at most 4 (steps use several cores each).
DEFAULT_WORKERS = max(2, min(4, os.cpu_count() or 1))
#: Runs (and dataset loads) that may wait for a worker in the default pool before more are refused.
DEFAULT_QUEUE = 32
#: Worker threads of the light pool (steps known to be quick) and of the pool that loads datasets.
LIGHT_WORKERS = 2
#: A step whose last successful run in the session took less than this (seconds) runs on the light pool.
LIGHT_SECONDS = 0.1
#: A worker idle this long (seconds) ends; the pool starts another when work comes.
WORKER_IDLE_SECONDS = 30.0
#: How much lower the workers' CPU priority is than that of the threads answering requests (Linux nice).
WORKER_NICENESS = 10

T = TypeVar("T")


class RunPool:
    """A bounded pool of daemon threads for the API's runs and dataset loads.

    At most ``workers`` jobs run at once and at most ``queue`` more wait, in order; one more is
    refused with :class:`TooManyRequests` (429) whose ``retry_after`` is estimated from how long
    recent jobs took. The event loop never runs a job, and a flood of runs cannot start a thread
    each. A job is a callable that handles its own errors (:meth:`call` wraps one that may raise).
    """

    def __init__(self, *, workers: int = DEFAULT_WORKERS, queue: int = DEFAULT_QUEUE) -> None:
        if workers < 1 or queue < 0:
            raise ValueError("a pool needs at least 1 worker and a queue of 0 or more, "
                             f"got {workers}, {queue}")
        self.workers = workers
        self.queue = queue
        self._jobs: SimpleQueue[Callable[[], None]] = SimpleQueue()
        self._lock = threading.Lock()
        self._held = 0  # jobs running or waiting
        self._running = 0
        self._threads: list[threading.Thread] = []
        self._mean_seconds = 1.0  # moving average of job durations, for Retry-After

    def stats(self) -> dict[str, int]:
        """``{"workers", "running", "queued", "max_queued"}`` now."""
        with self._lock:
            return {"workers": self.workers, "running": self._running, "queued": self._held - self._running,
                    "max_queued": self.queue}

    def reserve(self) -> bool:
        """Hold a place for one job (429 when none is left); True when a worker is free to take it now."""
        with self._lock:
            if self._held >= self.workers + self.queue:
                waiting = self._held - self._running
                wait = self._mean_seconds * (waiting + 1) / self.workers
                reason = (f"the server's workers run {self._running} steps or dataset loads with {waiting} "
                          f"more waiting (at most {self.workers} at once and {self.queue} waiting); "
                          "retry later")
                raise TooManyRequests("server", reason, retry_after=min(60.0, max(1.0, wait)))
            self._held += 1
            return self._held <= self.workers

    def release(self) -> None:
        """Give back a place held by :meth:`reserve` that will not be :meth:`start`-ed."""
        with self._lock:
            self._held -= 1

    def start(self, job: Callable[[], None]) -> None:
        """Run ``job`` on a worker (its place held by :meth:`reserve`) as soon as one is free."""
        with self._lock:  # with the lock, so that a worker about to leave sees the job
            self._jobs.put(job)
            if len(self._threads) < self.workers:
                thread = threading.Thread(target=self._work, name=f"lab-worker-{len(self._threads)}",
                                          daemon=True)
                self._threads.append(thread)
                thread.start()

    def submit(self, job: Callable[[], None]) -> bool:
        """:meth:`reserve` then :meth:`start`; True when it starts at once, False when it waits its turn."""
        now = self.reserve()
        self.start(job)
        return now

    async def call(self, func: Callable[[], T]) -> T:
        """``func()`` on a worker, awaited; its exception is raised here (429 when the pool is full)."""
        future: concurrent.futures.Future[T] = concurrent.futures.Future()

        def job() -> None:
            if not future.set_running_or_notify_cancel():  # the request went away while it waited
                return
            try:
                future.set_result(func())
            except BaseException as exc:  # handed to the awaiting request
                future.set_exception(exc)

        self.submit(job)
        return await asyncio.wrap_future(future)

    def _work(self) -> None:
        lower_priority(WORKER_NICENESS)
        while True:
            try:
                job = self._jobs.get(timeout=WORKER_IDLE_SECONDS)
            except Empty:
                with self._lock:
                    if self._jobs.empty():  # idle: leave (start makes a new worker when one is needed)
                        self._threads.remove(threading.current_thread())
                        return
                continue
            with self._lock:
                self._running += 1
            started = time.perf_counter()
            try:
                job()
            except BaseException:  # a job handles its own errors; never lose the worker
                log.exception("a worker job failed")
            finally:
                with self._lock:
                    self._running -= 1
                    self._held -= 1
                    self._mean_seconds = 0.8 * self._mean_seconds + 0.2 * (time.perf_counter() - started)


def step_response(session: Session, record: RunRecord) -> dict[str, Any]:
    """The JSON of one finished run: the RunRecord (params, seconds, metrics, warnings) plus context."""
    spec = session.pipeline.step(record.step)
    return {**record.to_json(), "session": session.id, "outputs": list(spec.writes),
            "steps": session.step_status(), "version": session.version}


def record_outcome(session: Session, record: RunRecord) -> tuple[str, dict[str, Any]]:
    """The final event for a history record: ``done`` with the run's JSON, or ``error`` with the error
    body."""
    if record.status == "ok":
        return "done", step_response(session, record)
    kind = "cancelled" if record.status == "cancelled" else "step_failed"
    return "error", {**error_body(kind, record.step, record.error), "step": record.step}


def lower_priority(niceness: int) -> None:
    """Lower the calling thread's CPU priority by ``niceness`` (Linux, where nice is per thread and
    threads it starts inherit it; elsewhere nothing), so that on a busy machine the event loop
    answering requests gets the CPU before the steps do."""
    if not sys.platform.startswith("linux"):
        return
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + niceness))
    except OSError:  # not allowed here: run at the normal priority
        pass


@dataclass(frozen=True)
class RunPools:
    """The app's bounded pools: ``heavy`` for run-until and any step not known to be quick;
    ``light`` for a step whose last successful run in the session took under LIGHT_SECONDS;
    ``loads`` for the dataset loads of new sessions.

    A light step that turns out slow (other controls) holds a light worker once; its record then
    sends it to the heavy pool next time.
    """

    heavy: RunPool
    light: RunPool
    loads: RunPool

    def for_step(self, session: Session, step: str) -> RunPool:
        for record in reversed(session.history):
            if record.step == step and record.status == "ok":
                return self.light if record.seconds < LIGHT_SECONDS else self.heavy
        return self.heavy

    def stats(self) -> dict[str, dict[str, int]]:
        return {"heavy": self.heavy.stats(), "light": self.light.stats(), "loads": self.loads.stats()}


class RunMonitor:
    """Progress and outcome of the latest run in one session, for event-stream subscribers.

    Events are ``(seq, name, data)`` with ``seq`` increasing over the monitor's life; names are
    ``progress`` (``{"step", "iteration", "total", "loss", "message"}``), ``done`` and ``error``.
    """

    def __init__(self, session: Session) -> None:
        self._lock = threading.Lock()
        self._events: deque[tuple[int, str, dict[str, Any]]] = deque(maxlen=MAX_EVENTS)
        self._seq = 0
        self._session = weakref.ref(session)  # never a strong reference: the monitor lives beside it
        self.run_id = 0
        self.active = False
        self.external = False
        self.job: RunJob | None = None
        self.last_progress: dict[str, Any] | None = None
        self._history_mark = 0
        self._orphan_since: float | None = None
        #: len(session.history) when the latest run ended: a longer history means newer runs elsewhere.
        self.history_at_finish = 0

    def _start_locked(self) -> None:
        self.run_id += 1
        self._events.clear()
        self.active = True
        self.last_progress = None
        self._orphan_since = None

    def _append_locked(self, name: str, data: dict[str, Any]) -> None:
        self._seq += 1
        self._events.append((self._seq, name, data))

    def busy_with(self) -> str | None:
        """What runs in the session now (a step name, or an API run about to start), else None."""
        session = self._session()
        running = session.running if session is not None else None
        job = self.job
        return running or (job.label if job is not None else None)

    def begin(self, job: RunJob) -> None:
        """Start an API run; SessionBusy when a run (API or viewer) is already in progress."""
        session = self._session()
        with self._lock:
            running = session.running if session is not None else None
            busy = running or (self.job.label if self.job else None)
            if busy is not None:
                raise SessionBusy("session", f"step {busy!r} is running in this session; wait for it or "
                                             "POST .../cancel")
            # a viewer run nobody watched to its end
            if self.active and self.external and session is not None:
                self._close_external_locked(session, force=True)
            self._start_locked()
            self.external = False
            self.job = job

    def progress(self, step: str, progress: Progress) -> None:
        """Session listener: called from the running thread for every progress snapshot."""
        data = jsonable({"step": step, **progress.to_json()})
        session = self._session()
        with self._lock:
            if (self.active and self.external and session is not None
                    and len(session.history) > self._history_mark):
                self._close_external_locked(session, force=True)  # an earlier viewer run nobody watched
            if not self.active:  # a run started elsewhere (the viewer): follow it too
                self._start_locked()
                self.external = True
                self._history_mark = len(session.history) if session is not None else 0
            self.last_progress = data
            self._append_locked("progress", data)

    def finish(self, name: str, data: dict[str, Any]) -> None:
        session = self._session()
        with self._lock:
            self._finish_locked(session, name, data)

    def _finish_locked(self, session: Session | None, name: str, data: dict[str, Any]) -> None:
        self.history_at_finish = len(session.history) if session is not None else 0
        self._append_locked(name, data)
        self.active = False
        self.external = False
        self.job = None

    def poll(self, after: int) -> tuple[int, list[tuple[int, str, dict[str, Any]]], bool]:
        """``(run_id, events after seq `after`, active)``; also notices the end of a run started
        elsewhere."""
        self._check_external()
        with self._lock:
            return self.run_id, [e for e in self._events if e[0] > after], self.active

    def _check_external(self) -> None:
        session = self._session()
        if session is None:
            return
        with self._lock:
            if self.active and self.external and session.running is None:
                self._close_external_locked(session, force=False)
            else:
                self._orphan_since = None

    def _close_external_locked(self, session: Session, *, force: bool) -> None:
        """End a run started elsewhere with the outcome in the session's history."""
        if len(session.history) > self._history_mark:
            name, data = record_outcome(session, session.history[-1])
        else:  # the runner clears `running` a moment before it appends the record
            now = time.monotonic()
            self._orphan_since = self._orphan_since or now
            if not force and now - self._orphan_since < ORPHAN_SECONDS:
                return
            name, data = "error", error_body("internal", "session", "the run ended without a record")
        self._orphan_since = None
        self._finish_locked(session, name, data)


class RunRegistry:
    """One :class:`RunMonitor` per live session, dropped with the session (weak keys)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._monitors: weakref.WeakKeyDictionary[Session, RunMonitor] = weakref.WeakKeyDictionary()

    def monitor(self, session: Session) -> RunMonitor:
        with self._lock:
            monitor = self._monitors.get(session)
            if monitor is None:
                monitor = self._monitors[session] = RunMonitor(session)
                session.listeners.append(monitor.progress)
            return monitor


# --- checks before a run --------------------------------------------------------------------------
def _missing_input(session: Session, spec: StepSpec, name: str) -> MissingInput:
    producer = session.pipeline.producer(name)
    how = f"run step {producer.name!r} first" if producer else "upload it or pick a dataset that has it"
    return MissingInput(name, f"step {spec.name!r} reads {name!r}, which does not exist yet: {how}")


def check_idle(session: Session, monitor: RunMonitor) -> None:
    """SessionBusy (409) when a step runs in the session or an API run is about to start."""
    busy = monitor.busy_with()
    if busy is not None:
        raise SessionBusy("session", f"step {busy!r} is running in this session; wait for it or "
                                     "POST .../cancel")


def plan_step(session: Session, spec: StepSpec, controls: dict[str, Any] | None) -> dict[str, Any]:
    """Check one step can run now (controls 422, inputs 409); return its checked controls."""
    checked = spec.coerce_controls(controls)
    for inp in spec.inputs:
        if not inp.optional and inp.name not in session.state:
            raise _missing_input(session, spec, inp.name)
    return checked


def plan_until(session: Session, target: StepSpec, params: Mapping[str, Any] | None) -> Plan:
    """The plan ``run-until`` will run (:meth:`Session.plan`), every control and input checked first.

    ``params`` maps step names to controls; every entry is checked (field ``step.control``) before
    anything runs, so a bad control never leaves the session half-run. A step the target does not
    need (downstream of it, or on another branch) is refused: its controls would be ignored.
    """
    pipeline = session.pipeline
    params = dict(params or {})
    order = [s.name for s in pipeline.steps]
    upstream = pipeline.upstream(target.name)
    for name, controls in params.items():
        if name not in order:
            raise InvalidControl(name, f"module {pipeline.name!r} has no step {name!r}; steps are {order}")
        if name not in upstream:
            raise InvalidControl(name, f"step {name!r} is not one {target.name!r} needs (it comes after it "
                                       f"or on another branch of the data flow) and would not run; "
                                       f"{target.name!r} needs {list(upstream)}")
        if controls is not None and not isinstance(controls, dict):
            raise InvalidControl(name, "controls must be a JSON object")
        try:
            pipeline.step(name).coerce_controls(controls)
        except InvalidControl as exc:
            raise InvalidControl(f"{name}.{exc.field}", exc.reason) from None
    plan = session.plan(target.name, params)
    produced: set[str] = set()
    for name in plan.steps:
        spec = pipeline.step(name)
        for inp in spec.inputs:
            if not inp.optional and inp.name not in session.state and inp.name not in produced:
                raise _missing_input(session, spec, inp.name)
        produced.update(spec.writes)
    return plan


# --- the job ------------------------------------------------------------------------------------
class RunJob:
    """One API request's run (a step, or every step up to one), executed in a worker thread."""

    def __init__(self, session: Session, store: SessionStore, monitor: RunMonitor, *, step: str,
                 params: dict[str, Any] | None, until: bool = False) -> None:
        self.session = session
        self.store = store
        self.monitor = monitor
        self.step = step
        self.params = params
        self.until = until
        self.label = f"run-until {step}" if until else step
        self.current = step
        self.cancel_requested = threading.Event()
        self.finished = threading.Event()
        self.result: dict[str, Any] | None = None
        self.error: BaseException | None = None
        self._done_callbacks: list[Callable[[], object]] = []

    def add_done_callback(self, callback: Callable[[], object]) -> None:
        """Call ``callback`` (from the worker thread) when the run is over; add before starting. What
        it returns is ignored."""
        self._done_callbacks.append(callback)

    def _watch_cancel(self, step: str, progress: Progress) -> None:
        if self.cancel_requested.is_set():  # a cancel that arrived before the step took the lock
            self.session.cancel_event.set()

    def _start(self, step: str) -> None:
        self.current = step

    def _run_one(self, step: str, controls: dict[str, Any] | None) -> RunRecord:
        self._start(step)
        if self.cancel_requested.is_set():
            raise Cancelled(step, "cancelled by the user")
        return self.session.run(step, controls, on_progress=self._watch_cancel)

    def execute(self) -> None:
        """Run (in a worker thread); the outcome goes to ``result``/``error`` and to the monitor."""
        session = self.session
        try:
            if self.until:
                plan = plan_until(session, session.pipeline.step(self.step), self.params)
                records = session.run_plan(plan, self.params, on_start=self._start,
                                           should_stop=self.cancel_requested.is_set,
                                           on_progress=self._watch_cancel)
                self.result = {"session": session.id, "plan": plan.to_json(),
                               "ran": [r.step for r in records], "records": [r.to_json() for r in records],
                               "steps": session.step_status(), "version": session.version}
            else:
                self.result = step_response(session, self._run_one(self.step, self.params))
            self.store.check_memory()
            self.monitor.finish("done", self.result)
        except LabError as exc:
            self.error = exc
            self.monitor.finish("error", {**exc.to_dict(), "step": self.current})
        except Exception as exc:  # a bug in the runner, not in a step (Session.run wraps those)
            log.exception("run %s failed in session %s", self.label, session.id)
            self.error = exc
            self.monitor.finish("error", error_body("internal", "server", f"{type(exc).__name__}: {exc}"))
        finally:
            self.finished.set()
            for callback in self._done_callbacks:
                with contextlib.suppress(RuntimeError):  # the waiting event loop is gone (shutting down)
                    callback()

