"""Building a tab's widgets: the fixed GUI every tab has, and one folder per step of a pipeline.

:func:`build_tab_gui` adds, in order: the header and the error box; the module, dataset and
session pickers; the **Steps** folder with **Run all** and the "Re-run dependants automatically"
checkbox above the steps; the run **History** and the **Values**; and the media panel (Images and
Plots tabs) docked on the left. :func:`build_step_rows` adds one folder per step inside the Steps
folder: its summary, what it reads and writes, a widget per control (:mod:`lab.viewer.widgets`),
Run / Run to here / Reset, and right below them, for a long (generator) step, its progress (text,
bar, loss plot, Cancel: :class:`StepProgressGui`, hidden until it runs, where the user pressed
Run), then a note that says why it is stale, and its metrics. The Steps folder
(:class:`StepsFolder`) keeps the progress widgets of its current rows by step, for
:class:`lab.viewer.progress.ProgressPanel`; the Cancel buttons of every step are one
:class:`CancelButtons` (``TabGui.cancel_button``). Nothing here runs a step or reads a session:
the tab (:class:`lab.viewer.view.ClientView`) wires the callbacks.
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lab.core.pipeline import Pipeline
from lab.core.step import StepSpec
from lab.viewer.text import step_label
from lab.viewer.widgets import add_control_widget

log = logging.getLogger("lab.viewer")

#: Width in pixels of the panel of images and plots, docked on the left.
MEDIA_PANEL_WIDTH = 440
#: Width in pixels of the main (controls) panel, docked on the right.
MAIN_PANEL_WIDTH = 400
#: The buttons of every step, in order.
STEP_BUTTONS = ("Run", "Run to here", "Reset")
#: The label of the checkbox that makes Run re-run what depends on the step.
AUTO_RERUN_LABEL = "Re-run dependants automatically"


@dataclass
class TabGui:
    """The fixed widgets of one tab (see the module docstring), by role."""

    header: Any
    error_box: Any
    session_folder: Any
    module_dropdown: Any
    dataset_dropdown: Any
    dataset_options: Any
    new_button: Any
    session_id_text: Any
    open_button: Any
    steps_folder: StepsFolder
    run_all_button: Any
    auto_rerun: Any
    cancel_button: CancelButtons
    history_folder: Any
    history_md: Any
    values_folder: Any
    values_md: Any
    media_panel: Any
    images_tab: Any
    plots_tab: Any
    #: The browser tab's title (it shows the progress of the running step).
    title: TabTitle | None = None


#: The browser tab's title when no step runs.
PLAIN_TITLE = "Vision Lab"


class TabTitle:
    """The browser tab's title (``document.title``), set with one line of JavaScript (viser's
    ``RunJavascriptMessage``; viser has no title API) when it changes. ``value`` is the title last set."""

    def __init__(self, gui: Any) -> None:
        self.gui = gui
        self.value = ""
        self.set(PLAIN_TITLE)

    def set(self, title: str) -> None:
        if title == self.value:
            return
        self.value = title
        try:
            from viser import _messages

            self.gui._websock_interface.queue_message(
                _messages.RunJavascriptMessage(source=f"document.title = {json.dumps(title)};"))
        except Exception as exc:  # an older viser: the title is cosmetic
            log.info("could not set the tab title: %s", exc)


@dataclass(frozen=True)
class StepProgressGui:
    """The progress widgets in one long step's folder, below its buttons: the text, the bar, the loss
    plot and Cancel; ``folder`` is the step's folder (its label says the step's status)."""

    folder: Any
    text: Any
    bar: Any
    loss_plot: Any
    cancel: Any

    def show(self, visible: bool) -> None:
        """Show or hide the progress of this step (the loss plot only shows once there is a loss)."""
        self.text.visible = visible
        self.bar.visible = visible
        self.cancel.visible = visible
        if not visible:
            self.loss_plot.visible = False


@dataclass
class CancelButtons:
    """The Cancel buttons of every long step as one button: ``on_click`` callbacks run when any of them
    is pressed; ``disabled`` is shared."""

    buttons: list[Any] = field(default_factory=list)
    callbacks: list[Callable[[Any], None]] = field(default_factory=list)
    _disabled: bool = True

    def on_click(self, callback: Callable[[Any], None]) -> Callable[[Any], None]:
        self.callbacks.append(callback)
        return callback

    def click(self, event: Any) -> None:
        for callback in list(self.callbacks):
            callback(event)

    def add(self, button: Any) -> None:
        """A step's Cancel button: pressing it is pressing this one."""
        button.disabled = self._disabled
        button.on_click(self.click)
        self.buttons.append(button)

    @property
    def disabled(self) -> bool:
        return self._disabled

    @disabled.setter
    def disabled(self, value: bool) -> None:
        self._disabled = bool(value)
        for button in self.buttons:
            with contextlib.suppress(Exception):  # a removed button
                button.disabled = self._disabled


class StepsFolder:
    """The Steps folder: the viser folder (``with`` it to add inside; other attributes are the folder's),
    the progress widgets of the long steps of its current rows by step name (``progress``, replaced by
    every :func:`build_step_rows`), and the shared Cancel buttons."""

    __slots__ = ("cancel", "handle", "progress")

    def __init__(self, handle: Any, cancel: CancelButtons) -> None:
        self.handle = handle
        self.cancel = cancel
        self.progress: dict[str, StepProgressGui] = {}

    def __enter__(self) -> StepsFolder:
        self.handle.__enter__()
        return self

    def __exit__(self, *args: Any) -> None:
        self.handle.__exit__(*args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.handle, name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name in StepsFolder.__slots__:
            object.__setattr__(self, name, value)
        else:
            setattr(self.handle, name, value)


def _configure(gui: Any) -> None:
    with contextlib.suppress(Exception):  # an older viser without these options: the defaults are fine
        gui.configure_theme(control_width="large", show_share_button=False)


def _dock(gui: Any, media_panel: Any) -> None:
    try:
        media_panel.dock_left()
        media_panel.set_width(MEDIA_PANEL_WIDTH)
        gui.main_panel.dock_right()
        gui.main_panel.set_width(MAIN_PANEL_WIDTH)
    except Exception as exc:  # placement is cosmetic
        log.info("could not dock the image panel: %s", exc)


def build_tab_gui(gui: Any, module_names: Sequence[str]) -> TabGui:
    """Add a tab's fixed widgets to ``gui`` (a viser ``GuiApi``); the module picker offers
    ``module_names``."""
    _configure(gui)
    header = gui.add_markdown("**Vision Lab**", order=0)
    error_box = gui.add_markdown("", order=1, visible=False)
    session_folder = gui.add_folder("Module · dataset · session", order=2, expand_by_default=False)
    with session_folder:
        offered = list(module_names) or ["(none)"]
        module_dropdown = gui.add_dropdown("module", offered, initial_value=offered[0],
                                           hint="the teaching module")
        dataset_dropdown = gui.add_dropdown("dataset", ["(none)"], hint="the data the session starts from")
        dataset_options = gui.add_folder("dataset options", expand_by_default=False)
        new_button = gui.add_button("New session", hint="load the dataset into a fresh session")
        session_id_text = gui.add_text("session id", "", hint="a session made over REST: paste its id")
        open_button = gui.add_button("Open session", hint="show the session whose id is above")
    cancel_button = CancelButtons()
    steps_folder = StepsFolder(gui.add_folder("Steps", order=3), cancel_button)
    with steps_folder:
        run_all_button = gui.add_button("Run all", hint="run every step that is not done (missing or stale) "
                                                        "and every step that reads what those rewrite")
        auto_rerun = gui.add_checkbox(AUTO_RERUN_LABEL, True,
                                      hint="on: Run on a step also re-runs the steps that depend on it; off "
                                           "(for slow steps): Run runs only the step, the later ones then "
                                           "need a run")
    history_folder = gui.add_folder("History", order=5, expand_by_default=False)
    with history_folder:
        history_md = gui.add_markdown("No step has run yet.")
    values_folder = gui.add_folder("Values", order=6, expand_by_default=False)
    with values_folder:
        values_md = gui.add_markdown("")
    media_panel = gui.add_panel(visible=False)  # images and plots: a panel of their own, docked on the left
    images_tab = media_panel.add_tab("Images")
    plots_tab = media_panel.add_tab("Plots")
    _dock(gui, media_panel)
    return TabGui(header, error_box, session_folder, module_dropdown, dataset_dropdown, dataset_options,
                  new_button, session_id_text, open_button, steps_folder, run_all_button, auto_rerun,
                  cancel_button, history_folder, history_md, values_folder, values_md, media_panel,
                  images_tab, plots_tab, title=TabTitle(gui))


@dataclass
class StepRow:
    """The GUI of one step: its folder (label = number, title, status), control widgets by name,
    the Run / Run to here / Reset button group, the progress of a long step (None for others), the note
    that says why it is stale, and its metrics."""

    spec: StepSpec
    folder: Any
    controls: dict[str, Any]
    buttons: Any
    note: Any
    metrics: Any
    progress: StepProgressGui | None = None


def step_description(spec: StepSpec) -> str:
    """The text at the top of a step's folder: its summary and what it reads and writes."""
    reads = ", ".join(spec.reads) or "nothing"
    writes = ", ".join(spec.writes) or "metrics only"
    long = " Long step: shows progress, can be cancelled." if spec.is_generator else ""
    return f"{spec.summary}\n\n*reads* {reads} → *writes* {writes}.{long}"


def build_step_rows(gui: Any, container: Any, pipeline: Pipeline, status: Mapping[str, str],
                    ran_with: Mapping[str, Mapping[str, Any]]) -> dict[str, StepRow]:
    """One folder per step of ``pipeline`` in ``container`` (the Steps folder), labelled with ``status``;
    each control's widget shows what the step's outputs were computed with (``ran_with``), else its
    default. The first step that is not done is expanded."""
    current = next((s.name for s in pipeline.steps if status[s.name] != "done"), None)
    rows: dict[str, StepRow] = {}
    with container:
        for index, spec in enumerate(pipeline.steps):
            folder = gui.add_folder(step_label(index, spec, status[spec.name]),
                                    expand_by_default=spec.name == current)
            ran = ran_with.get(spec.name, {})
            with folder:
                gui.add_markdown(step_description(spec))
                controls = {c.name: add_control_widget(gui, c, ran.get(c.name)) for c in spec.controls}
                buttons = gui.add_button_group("step", STEP_BUTTONS)
                progress = add_step_progress(gui, folder) if spec.is_generator else None
                note = gui.add_markdown("", visible=False)
                metrics = gui.add_markdown("")
            rows[spec.name] = StepRow(spec, folder, controls, buttons, note, metrics, progress)
    if isinstance(container, StepsFolder):
        container.cancel.buttons = []  # those of the rows replaced are gone
        container.progress = {name: row.progress for name, row in rows.items() if row.progress is not None}
        for row in rows.values():
            if row.progress is not None:
                container.cancel.add(row.progress.cancel)
    return rows


def add_step_progress(gui: Any, folder: Any) -> StepProgressGui:
    """The hidden progress widgets of a long step, added where ``gui`` adds now (below its buttons)."""
    text = gui.add_markdown("", visible=False)
    bar = gui.add_progress_bar(0.0, animated=False, visible=False)
    loss_plot = gui.add_uplot((np.zeros(1), np.zeros(1)), ({"label": "iteration"}, {
        "label": "loss", "stroke": "#d62728", "width": 2}), title="loss", aspect=1.6,
        scales={"x": {"time": False}}, visible=False)
    cancel = gui.add_button("Cancel", color="red", hint="stop the running step", visible=False)
    return StepProgressGui(folder, text, bar, loss_plot, cancel)


__all__ = ["AUTO_RERUN_LABEL", "MAIN_PANEL_WIDTH", "MEDIA_PANEL_WIDTH", "PLAIN_TITLE", "STEP_BUTTONS",
           "CancelButtons", "StepProgressGui", "StepRow", "StepsFolder", "TabGui", "TabTitle",
           "add_step_progress", "build_step_rows", "build_tab_gui", "step_description"]
