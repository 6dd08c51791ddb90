"""Building a tab's widgets: the fixed GUI every tab has, and one folder per step of a pipeline.

:func:`build_tab_gui` adds, in order: the header and the error box; the module, dataset and
session pickers; the **Steps** folder with **Run all** and the "Re-run dependants automatically"
checkbox above the steps; the **Progress** folder of long steps (text, bar, loss plot, Cancel);
the run **History** and the **Values**; and the media panel (Images and Plots tabs) docked on the
left. :func:`build_step_rows` adds one folder per step inside the Steps folder: its summary, what
it reads and writes, a widget per control (:mod:`lab.viewer.widgets`), Run / Run to here / Reset,
a note that says why it is stale, and its metrics. Nothing here runs a step or reads a session:
the tab (:class:`lab.viewer.view.ClientView`) wires the callbacks.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
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
    steps_folder: Any
    run_all_button: Any
    auto_rerun: Any
    progress_folder: Any
    progress_text: Any
    progress_bar: Any
    loss_plot: Any
    cancel_button: Any
    history_folder: Any
    history_md: Any
    values_folder: Any
    values_md: Any
    media_panel: Any
    images_tab: Any
    plots_tab: Any


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
    steps_folder = gui.add_folder("Steps", order=3)
    with steps_folder:
        run_all_button = gui.add_button("Run all", hint="run every step that is not done (missing or stale) "
                                                        "and every step that reads what those rewrite")
        auto_rerun = gui.add_checkbox(AUTO_RERUN_LABEL, True,
                                      hint="on: Run on a step also re-runs the steps that depend on it; off "
                                           "(for slow steps): Run runs only the step, the later ones then "
                                           "need a run")
    progress_folder = gui.add_folder("Progress", order=4, visible=False)
    with progress_folder:
        progress_text = gui.add_markdown("")
        progress_bar = gui.add_progress_bar(0.0, animated=False)
        loss_plot = gui.add_uplot((np.zeros(1), np.zeros(1)), ({"label": "iteration"}, {
            "label": "loss", "stroke": "#d62728", "width": 2}), title="loss", aspect=1.6,
            scales={"x": {"time": False}})
        cancel_button = gui.add_button("Cancel", color="red", hint="stop the running step")
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
                  progress_folder, progress_text, progress_bar, loss_plot, cancel_button, history_folder,
                  history_md, values_folder, values_md, media_panel, images_tab, plots_tab)


@dataclass
class StepRow:
    """The GUI of one step: its folder (label = number, title, status), control widgets by name,
    the Run / Run to here / Reset button group, the note that says why it is stale, and its metrics."""

    spec: StepSpec
    folder: Any
    controls: dict[str, Any]
    buttons: Any
    note: Any
    metrics: Any


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
                note = gui.add_markdown("", visible=False)
                metrics = gui.add_markdown("")
            rows[spec.name] = StepRow(spec, folder, controls, buttons, note, metrics)
    return rows


__all__ = ["AUTO_RERUN_LABEL", "MAIN_PANEL_WIDTH", "MEDIA_PANEL_WIDTH", "STEP_BUTTONS", "StepRow", "TabGui",
           "build_step_rows", "build_tab_gui", "step_description"]
