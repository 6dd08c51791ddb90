"""Progress of long (generator) steps in a tab: the text, the bar, the live loss plot and Cancel.

A :class:`ProgressPanel` listens to a session (``session.listeners``): every
:class:`~lab.core.step.Progress` snapshot of a long step (run by this tab, or by a REST call on the
same session) updates the panel at most every :data:`PROGRESS_SECONDS`, and a snapshot's preview
values (``Progress.values``) are handed to ``preview`` at most every :data:`PREVIEW_SECONDS`. When
the step ends, :meth:`ProgressPanel.finish` shows how (it may stop early, converged).
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
from lab.viewer.gui import TabGui
from lab.viewer.text import format_number

#: Minimum time between two GUI updates from progress snapshots (and between two preview draws).
PROGRESS_SECONDS = 0.1
PREVIEW_SECONDS = 0.5


@dataclass
class ProgressState:
    """What the panel shows of the current long step: its snapshots' losses, the bar and the message."""

    step: str | None = None
    iteration: int = -1
    x: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    shown: float = 0.0
    preview: float = 0.0
    finished: bool = False
    log: bool = False
    fraction: float = 0.0
    animated: bool = False
    message: str = ""


def progress_message(step: str, progress: Progress) -> str:
    """The panel's text for a snapshot: ``**step**: iteration i/total, loss L — message``."""
    total = progress.total
    loss = "" if progress.loss is None else f", loss {format_number(progress.loss)}"
    note = f" — {progress.message}" if progress.message else ""
    return f"**{step}**: iteration {progress.iteration}{f'/{total}' if total else ''}{loss}{note}"


class ProgressPanel:
    """The Progress folder of one tab (see the module docstring). ``lock`` is the tab's; ``preview(values)``
    draws a snapshot's preview values over the session's state."""

    def __init__(self, gui: TabGui, lock: threading.RLock,
                 preview: Callable[[Mapping[str, Any]], None]) -> None:
        self.gui = gui
        self.lock = lock
        self.preview = preview
        self.state = ProgressState()
        self.closed = False

    def on_progress(self, step: str, progress: Progress) -> None:
        """Session listener: called from the thread running a long step (this tab's or a REST call's)."""
        if self.closed:
            return
        state = self.state
        now = time.monotonic()
        new_run = step != state.step or progress.iteration <= state.iteration
        if new_run:
            self.state = state = ProgressState(step=step)
        state.iteration = progress.iteration
        if progress.loss is not None and np.isfinite(progress.loss):
            state.x.append(float(progress.iteration))
            state.y.append(float(progress.loss))
        total = progress.total
        state.fraction = min(1.0, progress.iteration / total) if total else 0.0
        state.animated = not total
        state.message = progress_message(step, progress)
        last = total is not None and progress.iteration >= total
        if not new_run and not last and now - state.shown < PROGRESS_SECONDS:
            return  # shown at the next snapshot, or when the step ends
        state.shown = now
        with self.lock:
            self.show(reset_scale=new_run)
            if progress.values and now - state.preview >= PREVIEW_SECONDS:
                state.preview = now
                self.preview(progress.values)

    def show(self, *, reset_scale: bool = False) -> None:
        """Put the latest snapshot on screen (bar, text, loss plot, log scale when it spans decades)."""
        state, gui = self.state, self.gui
        gui.progress_folder.visible = True
        gui.cancel_button.disabled = False
        gui.progress_bar.animated = state.animated
        gui.progress_bar.value = 100.0 * state.fraction
        gui.progress_text.content = state.message
        if state.x:
            xs, ys = np.asarray(state.x), np.asarray(state.y)
            gui.loss_plot.data = (xs, ys)
            log_scale = bool(ys.min() > 0 and ys.max() / ys.min() > 100)
            if reset_scale or log_scale != state.log:
                state.log = log_scale
                scales: dict[str, Any] = {"x": {"time": False}}
                if log_scale:
                    scales["y"] = {"distr": 3, "log": 10}
                gui.loss_plot.scales = scales

    def idle(self, history: Sequence[RunRecord]) -> None:
        """No step runs: nothing to cancel; show how the last long step ended."""
        self.gui.progress_bar.animated = False
        self.gui.cancel_button.disabled = True
        self.finish(history)

    def finish(self, history: Sequence[RunRecord]) -> None:
        """After a long step: show its last snapshot and how it ended (it may stop early, converged)."""
        state = self.state
        if state.step is None or state.finished:
            return
        record = next((r for r in reversed(history) if r.step == state.step), None)
        if record is None:
            return
        state.finished = True
        self.show()
        self.gui.cancel_button.disabled = True
        self.gui.progress_bar.animated = False
        if record.status == "ok":
            self.gui.progress_bar.value = 100.0
        self.gui.progress_text.content = f"{state.message} — **{record.status}**"


__all__ = ["PREVIEW_SECONDS", "PROGRESS_SECONDS", "ProgressPanel", "ProgressState", "progress_message"]
