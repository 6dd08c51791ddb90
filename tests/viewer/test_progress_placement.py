"""Progress of a long step where the eye is: in the step's own folder (below its Run buttons) and in the
browser tab's title while it runs; a finished run's progress goes when its step is reset or goes stale;
the loss plot's x axis ends at the iterations run, and a log axis has no "0" tick."""

from __future__ import annotations

import dataclasses
from collections.abc import Generator
from typing import Annotated

import numpy as np
import pytest

from lab.core import Loaded, Pipeline, Progress, Range
from lab.core.step import step_result
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.gui import PLAIN_TITLE
from lab.viewer.plots import chart_axes, decade_label, log_axis
from lab.viewer.progress import running_title
from toy_pipeline import TOY


def make_view(server, store, modules=None) -> ClientView:
    view = ClientView(server, store, ModuleCatalog(modules or {"toy": TOY}), is_client=False, background=False)
    view.start({})
    return view


@pytest.fixture
def view(server, store):
    return make_view(server, store)


def scripts(server) -> list[str]:
    """Record the JavaScript the server sends its clients (the tab title is set that way)."""
    from viser import _messages

    sent: list[str] = []
    interface = server.gui._websock_interface
    queue = interface.queue_message

    def spy(message):
        if isinstance(message, _messages.RunJavascriptMessage):
            sent.append(message.source)
        return queue(message)

    interface.queue_message = spy
    return sent


def test_progress_widgets_live_in_the_long_steps_folder_below_its_buttons(view):
    row = view.rows["lift"]
    progress = row.progress
    assert progress is not None and progress.folder is row.folder
    folder_id = row.folder._impl.uuid
    for handle in (progress.text, progress.bar, progress.loss_plot, progress.cancel):
        assert handle._impl.parent_container_id == folder_id
        assert row.buttons.order < handle.order < row.note.order  # right below Run / Run to here / Reset
        assert not handle.visible  # until the step runs
    assert view.rows["add_noise"].progress is None  # not a long step: no progress widgets
    assert view.tab.steps_folder.progress == {"lift": progress}
    view.press("lift", "Run to here")
    assert progress.text.visible and progress.bar.visible and progress.loss_plot.visible
    assert progress.text.content.startswith("**lift**: iteration 5/5") and "**ok**" in progress.text.content


def test_a_steps_cancel_button_cancels_through_the_tabs_callbacks(view):
    pressed = []
    view.tab.cancel_button.on_click(lambda event: pressed.append(event))
    view.tab.steps_folder.cancel.click("event")
    assert pressed == ["event"]
    view.tab.cancel_button.disabled = False
    assert not view.rows["lift"].progress.cancel.disabled
    view.tab.cancel_button.disabled = True
    assert view.rows["lift"].progress.cancel.disabled


def test_the_tab_title_shows_the_running_step_and_comes_back(server, view):
    sent = scripts(server)
    titles = []
    view.session.listeners.append(lambda step, progress: titles.append(view.tab.title.value))
    assert view.tab.title.value == PLAIN_TITLE
    view.press("lift", "Run to here")
    assert titles[0] == "▶ lift 1/5 — Vision Lab" and titles[-1] == "▶ lift 5/5 — Vision Lab"
    assert view.tab.title.value == PLAIN_TITLE  # the step ended
    assert 'document.title = "\\u25b6 lift 1/5 \\u2014 Vision Lab";' in sent
    assert sent[-1] == 'document.title = "Vision Lab";'
    assert running_title("refine_calibration", 7, 100) == "▶ refine_calibration 7/100 — Vision Lab"
    assert running_title("sample", 3, None) == "▶ sample 3 — Vision Lab"


def test_a_reset_step_no_longer_shows_its_old_progress(view):
    view.press("lift", "Run to here")
    progress = view.rows["lift"].progress
    assert progress.text.visible
    view.press("lift", "Reset")
    assert not (progress.text.visible or progress.bar.visible or progress.loss_plot.visible or progress.cancel.visible)
    assert "lift" not in view.progress.states
    view.press("lift", "Run")  # a new run shows its own progress again
    assert progress.text.visible and "**ok**" in progress.text.content


def test_a_stale_step_no_longer_shows_its_old_progress(view):
    view.press("lift", "Run to here")
    progress = view.rows["lift"].progress
    view.rows["lift"].controls["iterations"].value = 7  # lift is stale now
    view.refresh(force=True)
    assert view.rows["lift"].folder.label.endswith("stale")
    assert not progress.text.visible


def test_a_reset_upstream_hides_a_finished_downstream_runs_progress(view):
    view.press("lift", "Run to here")
    view.press("add_noise", "Reset")  # lift's outputs go with it
    assert not view.rows["lift"].progress.text.visible


def test_a_rerun_without_progress_hides_the_old_runs(view):
    view.press("lift", "Run to here")
    progress = view.rows["lift"].progress
    assert progress.text.visible
    again = dataclasses.replace(view.session.history[-1])  # lift ran again (a student's code) without snapshots
    view.session.history.append(again)
    view.refresh(force=True)
    assert view.rows["lift"].folder.label.endswith("done") and not progress.text.visible


# --- a Levenberg-Marquardt-like step: converged after 7 of at most 100 iterations -------------------
@step_result
class Fitted:
    fitted: np.ndarray


def refine(*, max_iterations: Annotated[int, Range(1, 1000)] = 100) -> Generator[Progress, None, Fitted]:
    """Stop once converged (7 iterations); the loss falls over decades."""
    for i in range(7):
        yield Progress(iteration=i + 1, total=max_iterations, loss=10.0 ** -i)
    return Fitted(np.zeros(1))


def nothing() -> Loaded:
    return Loaded({})


REFINE = Pipeline.build(name="refine", title="Refine", summary="", steps=[refine], datasets=[nothing])


def test_the_loss_plot_ends_at_the_iterations_run_and_labels_every_decade(server, store):
    view = make_view(server, store, {"refine": REFINE})
    view.press("refine", "Run")
    plot = view.rows["refine"].progress.loss_plot
    assert list(plot.data[0]) == [1, 2, 3, 4, 5, 6, 7]
    assert plot.scales["x"] == {"time": False, "range": [1.0, 7.0]}  # not 100, the planned total
    assert plot.scales["y"] == {"distr": 3, "log": 10, "range": [pytest.approx(1e-6), 1.0]}
    labels = plot.axes[1]["values"]
    assert "0" not in labels and labels[0] == "1e-6" and labels[-1] == "1"
    assert plot.axes[1]["splits"] == pytest.approx([10.0 ** k for k in range(-6, 1)])
    assert "7/100" in view.rows["refine"].progress.text.content and "**ok**" in view.rows["refine"].progress.text.content


def test_a_log_axis_of_a_schedule_has_no_zero_tick():
    betas = np.linspace(1e-4, 0.02, 1000)
    abar = np.cumprod(1 - betas)
    y = np.stack([betas, abar, np.sqrt(abar), np.sqrt(1 - abar)])
    scales, axes = chart_axes(np.arange(1000.0), y)
    assert scales["y"]["distr"] == 3 and axes is not None and scales["y"]["range"] == pytest.approx([1e-5, 1.0])
    assert axes[1] == log_axis(y.ravel())
    assert "0" not in axes[1]["values"] and all(float(v) > 0 for v in axes[1]["values"])
    assert axes[1]["values"] == ["1e-5", "1e-4", "0.001", "0.01", "0.1", "1"]
    assert axes[1]["splits"] == pytest.approx([1e-5, 1e-4, 1e-3, 1e-2, 0.1, 1.0])
    assert scales["x"]["range"] == [0.0, 999.0]


def test_decade_labels_are_short_and_never_zero():
    assert [decade_label(k) for k in (-7, -4, -3, -1, 0, 2, 3, 4, 9)] == [
        "1e-7", "1e-4", "0.001", "0.1", "1", "100", "1000", "1e4", "1e9"]
    assert log_axis(np.array([0.0, -1.0])) == {}  # nothing positive: no log axis


def test_a_linear_axis_is_left_to_uplot():
    scales, axes = chart_axes(np.arange(3.0), np.array([1.0, 2.0, 3.0]))
    assert axes is None and "y" not in scales and scales["x"]["range"] == [0.0, 2.0]
    assert chart_axes(np.array([4.0]), np.array([1.0]))[0]["x"]["range"] == [4.0, 5.0]  # one point


def test_another_session_starts_with_no_progress_shown(view, store):
    view.press("lift", "Run to here")
    view.open_session(store.create(TOY))
    progress = view.rows["lift"].progress
    assert not progress.text.visible and view.progress.states == {}
    view.press("lift", "Run to here")
    assert progress.text.visible and "**ok**" in progress.text.content
