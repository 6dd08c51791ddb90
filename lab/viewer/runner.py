"""Running steps from a tab: what each button plans (through the core's one planner) and the worker
thread that runs the plan off viser's threads.

What runs is always decided by :meth:`lab.core.Pipeline.plan` (through :meth:`Session.plan`), never
by a loop of the viewer's own:

* **Run** on a step (:func:`step_plan`): the step, on the inputs there are, and with "Re-run
  dependants automatically" on, every step downstream whose outputs the run replaces (the
  planner's ``dependants``). Steps upstream of it never run here, even when stale: that is Run to
  here. A missing input is reported by the run, as :meth:`Session.run` words it.
* **Run to here**: :meth:`Session.plan` of the step with the controls shown, what the step needs
  by data flow and nothing else (texture's ``quilt``, which reads only ``sample``, runs alone).
* **Run all**: :meth:`Session.plan` with no target, every missing or stale step and what reads
  their outputs.

A :class:`Runner` executes a plan with :meth:`Session.run_plan` in the tab's one worker thread:
each step's label says "running" while it runs, the tab is redrawn after each step (:attr:`Runner.planned`
says which steps of the plan are still to finish), Cancel stops a
long step at its next snapshot and a plan before its next step. A step whose module's fast kernels are not
compiled in this process yet (:func:`lab.core.kernels.needs_compiling`: ``vision-lab serve`` compiles them
at start-up, so this is rare) is labelled :data:`COMPILING` instead, so a first run's pause to compile is
not taken for a hang.
"""

from __future__ import annotations

import logging
import threading
import traceback
from collections.abc import Callable
from typing import Any

from lab.core import kernels
from lab.core.errors import LabError
from lab.core.pipeline import Plan, RunRecord, Session, StepParams

log = logging.getLogger("lab.viewer")

#: The label of a running step that compiles its kernels first (see the module docstring).
COMPILING = "… running: compiling fast kernels once (~20 s); cached afterwards"


def running_label(session: Session, step: str) -> str:
    """What the label of ``step`` says while it runs: "running", or :data:`COMPILING` when running it now
    compiles kernels first."""
    return COMPILING if kernels.needs_compiling(session.pipeline.name, step) else "running"


def step_plan(session: Session, step: str, *, dependants: bool) -> Plan:
    """What the Run button of ``step`` runs (see the module docstring): the step and, with ``dependants``,
    the steps downstream whose outputs its run replaces. Its own inputs count as there, so the planner adds
    nothing upstream; when one is missing, running the plan says which and how to make it."""
    spec = session.pipeline.step(step)
    available = set(session.state) | set(spec.reads)
    return session.pipeline.plan(step, available, dependants=dependants)


class Runner:
    """The worker of one tab: runs one job at a time, in a background thread (inline when ``background`` is
    False, for tests). What a job raises is shown with ``show_error``; ``refresh()`` redraws the tab after
    it, and ``mark(step, status)`` labels a step while a plan runs it."""

    def __init__(self, *, background: bool, show_error: Callable[[BaseException], None],
                 refresh: Callable[[], None], mark: Callable[[str, str], None]) -> None:
        self.background = background
        self.show_error = show_error
        self.refresh = refresh
        self.mark = mark
        self.worker: threading.Thread | None = None
        #: The steps of the running plan that have not finished (the running one first); () when none runs.
        self.planned: tuple[str, ...] = ()
        self._stop = threading.Event()

    def busy(self) -> bool:
        """Whether a job is running in the worker thread."""
        return self.worker is not None and self.worker.is_alive()

    def in_background(self, job: Callable[[], Any], name: str) -> None:
        """Run ``job`` in the worker thread (off viser's threads); refused while another job runs."""
        if self.busy():
            raise LabError(name, "the tab is still busy with the last step or comparison; wait or press "
                                 "Cancel")
        if self.background:
            self.worker = threading.Thread(target=self._work, args=(job,), name=f"lab-viewer-{name}",
                                           daemon=True)
            self.worker.start()
        else:
            self._work(job)

    def run_plan(self, session: Session, plan: Plan, params: StepParams,
                 override: Callable[[str], Callable[..., Any] | None] | None = None) -> None:
        """Run ``plan`` on ``session`` with these controls (``{step: controls}``) in the worker thread; each
        step is labelled "running" while it runs and the tab is redrawn after it. ``override(step)`` is the
        function run in place of a step (None: the step's own), asked in the worker: what it raises (no
        student code loaded) is shown like a failing step."""
        if self.busy():
            raise LabError("step", f"step {session.running or '...'} is still running; wait or press Cancel")
        self._stop.clear()
        steps = plan.steps
        if not steps:
            self.refresh()
            return
        self.mark(steps[0], running_label(session, steps[0]))
        self.planned = tuple(steps)

        def after(record: RunRecord) -> None:
            index = steps.index(record.step)
            self.planned = tuple(steps[index + 1:])
            if index + 1 < len(steps):
                self.refresh()
                self.mark(steps[index + 1], running_label(session, steps[index + 1]))

        def job() -> None:
            replaced = {name: f for name in steps
                        if override is not None and (f := override(name)) is not None}
            session.run_plan(plan, params, overrides=replaced, on_step=after, should_stop=self._stop.is_set)

        self.in_background(job, steps[-1])

    def cancel(self, session: Session) -> bool:
        """Stop what runs: the long step at its next snapshot, this tab's plan before its next step.
        False when nothing runs."""
        stopped = session.cancel()
        if self.busy():
            self._stop.set()
            stopped = True
        return stopped

    def wait(self, timeout: float = 30.0) -> None:
        """Wait for the job in the worker thread to end (tests)."""
        worker = self.worker
        if worker is not None:
            worker.join(timeout)

    def _work(self, job: Callable[[], Any]) -> None:
        try:
            job()
        except LabError as exc:
            self.show_error(exc)
        except Exception as exc:  # a bug somewhere: show it, keep the tab alive
            log.error("step failed in the viewer:\n%s", traceback.format_exc())
            self.show_error(exc)
        finally:
            self.planned = ()  # the last refresh labels every step as the session now is
            try:
                self.refresh()
            except Exception as exc:
                log.error("refresh failed:\n%s", traceback.format_exc())
                self.show_error(exc)


__all__ = ["COMPILING", "Runner", "running_label", "step_plan"]
