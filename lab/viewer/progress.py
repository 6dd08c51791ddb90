"""Progress of long (generator) steps in a tab: in the running step's own folder, and in the tab title.

A :class:`ProgressPanel` listens to a session (``session.listeners``): every
:class:`~lab.core.step.Progress` snapshot of a long step (run by this tab, or by a REST call on the
same session) updates that step's progress widgets (text, bar, live loss plot, Cancel: a
:class:`~lab.viewer.gui.StepProgressGui` below the step's Run buttons, where the user pressed Run) and
the browser tab's title (``▶ refine 7/100 — Vision Lab``) at most every :data:`PROGRESS_SECONDS`.

A snapshot's preview values (``Progress.values``: SfM's cameras and points as they register) are drawn by
``preview`` in the step's thread, so drawing is what watching costs (issue 16: an SfM run took 7 times as
long with a tab open). They are throttled to what a person can follow: the first snapshot's at once,
then at most one every :data:`PREVIEW_SECONDS`, and never more than :data:`PREVIEW_SHARE` of the step
thread's CPU time (a draw that took ``d`` CPU seconds waits until the thread has used ``d / PREVIEW_SHARE``
more; on a loaded machine a wall-time share would let a slow draw take most of the step's CPU). Values
that arrive meanwhile are kept, the latest replacing older ones, and drawn at the first snapshot past the
wait; when the step ends the pending ones are dropped: the step's result is drawn by the tab's refresh.
Unchanged values are not sent again (the renderers' fingerprints, :class:`lab.viewer.renderers.StateDrawer`).

When the step ends, :meth:`ProgressPanel.finish` shows how (it may stop early, converged) and the title
is plain again. A finished run's progress stays in its step's folder only while the step's status is the
one the run left: once the step is reset (or re-labelled stale, seen at the next refresh) it is hidden,
so it never contradicts the step's label.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lab.core.pipeline import RunRecord
from lab.core.step import Progress
from lab.viewer.gui import PLAIN_TITLE, StepProgressGui, TabGui
from lab.viewer.plots import chart_axes, set_uplot
from lab.viewer.text import format_number

#: Minimum time between two GUI updates from progress snapshots, and between two preview draws.
PROGRESS_SECONDS = 0.1
PREVIEW_SECONDS = 0.5
#: Most of a step's time its preview draws may take (see the module docstring).
PREVIEW_SHARE = 0.2
#: Minimum time between two tab titles of a running step (each is a line of JavaScript viser never culls).
TITLE_SECONDS = 1.0


@dataclass
class ProgressState:
    """What is shown of one long step's run: its snapshots' losses, the bar and the message; ``label``
    is its folder's label when the run ended (the step's status then)."""

    step: str | None = None
    iteration: int = -1
    total: int | None = None
    x: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    shown: float = 0.0
    #: When the next preview may be drawn (the panel's clock, and its step thread's CPU clock), and the values
    #: waiting for it.
    preview_at: float = 0.0
    preview_cpu_at: float = 0.0
    pending: Mapping[str, Any] | None = None
    previews: int = 0
    finished: bool = False
    fraction: float = 0.0
    animated: bool = False
    message: str = ""
    label: str | None = None
    record: RunRecord | None = None
    titled: float = -1e9


def progress_message(step: str, progress: Progress) -> str:
    """The panel's text for a snapshot: ``**step**: iteration i/total, loss L — message``."""
    total = progress.total
    loss = "" if progress.loss is None else f", loss {format_number(progress.loss)}"
    note = f" — {progress.message}" if progress.message else ""
    return f"**{step}**: iteration {progress.iteration}{f'/{total}' if total else ''}{loss}{note}"


def running_title(step: str, iteration: int, total: int | None) -> str:
    """The tab title while ``step`` runs: ``▶ step 7/100 — Vision Lab``."""
    count = f"{iteration}/{total}" if total else f"{iteration}"
    return f"▶ {step} {count} — {PLAIN_TITLE}"


class ProgressPanel:
    """The progress of one tab's long steps (see the module docstring). ``lock`` is the tab's;
    ``preview(values)`` draws a snapshot's preview values over the session's state; ``clock`` and
    ``cpu_clock`` are ``time.monotonic`` and ``time.thread_time`` (tests give others)."""

    def __init__(self, gui: TabGui, lock: threading.RLock,
                 preview: Callable[[Mapping[str, Any]], None], *,
                 clock: Callable[[], float] = time.monotonic,
                 cpu_clock: Callable[[], float] = time.thread_time) -> None:
        self.gui = gui
        self.lock = lock
        self.preview = preview
        self.clock = clock
        self.cpu_clock = cpu_clock
        self.states: dict[str, ProgressState] = {}
        self.current: str | None = None  # the step that reported last
        self.closed = False
        self._rows: dict[str, StepProgressGui] = {}

    @property
    def state(self) -> ProgressState:
        """The state of the step that reported last (an empty one before any)."""
        return self.states.get(self.current or "", ProgressState())

    def widgets(self, step: str) -> StepProgressGui | None:
        """The progress widgets in ``step``'s folder (None: the step has none); forgets the runs of rows
        that were rebuilt (another session)."""
        rows = self.gui.steps_folder.progress
        if rows is not self._rows:
            self._rows = rows
            self.states = {s: st for s, st in self.states.items() if s == self.current and not st.finished}
        return rows.get(step)

    def on_progress(self, step: str, progress: Progress) -> None:
        """Session listener: called from the thread running a long step (this tab's or a REST call's)."""
        if self.closed:
            return
        state = self.states.get(step)
        now = self.clock()
        new_run = state is None or state.finished or progress.iteration <= state.iteration
        if state is None or new_run:
            state = ProgressState(step=step)
            self.states[step] = state
        self.current = step
        state.iteration, state.total = progress.iteration, progress.total
        if progress.loss is not None and np.isfinite(progress.loss):
            state.x.append(float(progress.iteration))
            state.y.append(float(progress.loss))
        total = progress.total
        state.fraction = min(1.0, progress.iteration / total) if total else 0.0
        state.animated = not total
        state.message = progress_message(step, progress)
        if progress.values:
            state.pending = {**(state.pending or {}), **progress.values}
        last = total is not None and progress.iteration >= total
        if not new_run and not last and now - state.shown < PROGRESS_SECONDS:
            return  # shown at the next snapshot, or when the step ends
        state.shown = now
        with self.lock:
            self.show(state)
            if new_run or last or now - state.titled >= TITLE_SECONDS:
                state.titled = now
                self._title(running_title(step, progress.iteration, total))
            due = now >= state.preview_at and self.cpu_clock() >= state.preview_cpu_at
            if state.pending is not None and due:
                self._draw_preview(state)

    def _draw_preview(self, state: ProgressState) -> None:
        """Draw the pending preview values; the next may come :data:`PREVIEW_SECONDS` later, and once the
        step's thread has used this draw's CPU time over :data:`PREVIEW_SHARE` more."""
        values, state.pending = state.pending or {}, None
        started, cpu = self.clock(), self.cpu_clock()
        try:
            self.preview(values)
        finally:
            state.previews += 1
            state.preview_at = started + PREVIEW_SECONDS
            state.preview_cpu_at = cpu + (self.cpu_clock() - cpu) / PREVIEW_SHARE

    def _title(self, title: str) -> None:
        if self.gui.title is not None:
            self.gui.title.set(title)

    def show(self, state: ProgressState) -> None:
        """Put a step's latest snapshot on screen, in its folder (bar, text, loss plot whose x axis ends
        at the last iteration, log scale with a label per decade when the losses span decades), every widget
        changed in place (they are made once per step row: :func:`lab.viewer.gui.add_step_progress`)."""
        widgets = self.widgets(state.step or "")
        if widgets is None:
            return
        widgets.show(True)
        widgets.cancel.disabled = state.finished
        widgets.bar.animated = state.animated and not state.finished
        widgets.bar.value = 100.0 * state.fraction
        widgets.text.content = state.message
        if state.x:
            xs, ys = np.asarray(state.x), np.asarray(state.y)
            scales, axes = chart_axes(xs, ys)
            set_uplot(widgets.loss_plot, data=(xs, ys), scales=scales, axes=axes)
            widgets.loss_plot.visible = True

    def idle(self, history: Sequence[RunRecord]) -> None:
        """No step runs: nothing to cancel, a plain tab title; show how the last long step ended, and hide
        the finished runs of steps whose status changed since."""
        self.gui.cancel_button.disabled = True
        self._title(PLAIN_TITLE)
        self.finish(history)
        self.forget_changed(history)

    def finish(self, history: Sequence[RunRecord]) -> None:
        """After a long step: show its last snapshot and how it ended (it may stop early, converged)."""
        for state in list(self.states.values()):
            if state.finished or state.step is None:
                continue
            record = next((r for r in reversed(history) if r.step == state.step), None)
            if record is None:
                continue
            state.finished, state.record, state.pending = True, record, None  # the refresh draws the result
            if record.status == "ok":
                state.fraction = 1.0
            state.message = f"{state.message} — **{record.status}**"
            self.show(state)
            widgets = self.widgets(state.step)
            state.label = None if widgets is None else widgets.folder.label

    def forget_changed(self, history: Sequence[RunRecord] | None = None) -> None:
        """Hide the progress of finished runs whose step's label changed since (reset, stale), or that ran
        again without progress (``history``: its last record of the step is another)."""
        for step, state in list(self.states.items()):
            widgets = self.widgets(step)
            if not state.finished or widgets is None:
                continue
            latest = None if history is None else next((r for r in reversed(history) if r.step == step), None)
            if widgets.folder.label == state.label and (history is None or latest is state.record):
                continue
            widgets.show(False)
            self.states.pop(step, None)


__all__ = ["PREVIEW_SECONDS", "PREVIEW_SHARE", "PROGRESS_SECONDS", "TITLE_SECONDS", "ProgressPanel",
           "ProgressState", "progress_message", "running_title"]
