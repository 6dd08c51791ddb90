"""The GUI generated from a pipeline (the toy one): widgets match each control's schema, buttons
run / run to here / reset through the session, errors are shown and never raised, progress of long
steps is plotted, Cancel works, and changes made behind the viewer's back (REST) are redrawn."""

from __future__ import annotations

import time
from typing import Annotated, Literal
from collections.abc import Generator

import numpy as np
import pytest
import viser

from lab.core.step import step_result
from lab.core import Image, ImageSet, Loaded, Pipeline, Progress, Range, SessionStore, metric
from lab.viewer.app import (ClientView, ModuleCatalog, add_control_widget, format_number, metrics_markdown,
                            nice_step, widget_kind, widget_value)
from toy_pipeline import TOY


def make_view(server, store, modules=None, **kwargs) -> ClientView:
    """A view on the server's shared GUI, running steps inline (no browser needed)."""
    kwargs.setdefault("background", False)
    return ClientView(server, store, ModuleCatalog(modules or {"toy": TOY}), is_client=False, **kwargs)


@pytest.fixture
def view(server, store):
    view = make_view(server, store)
    view.start({})
    return view


# --- a pipeline with every kind of control ----------------------------------------------------------
@step_result
class Echo:
    echoed: np.ndarray
    total: float = metric("sum of the numbers", unit="px")


def every_control(images: ImageSet, *, flag: bool = True, label: str = "hi",
                  bounded: Annotated[float, Range(0.1, 10.0)] = 1.0, free: float = 2.5,
                  small: Annotated[int, Range(0, 20)] = 4, big: Annotated[int, Range(0, 100000)] = 7,
                  unbounded_int: int = 3, choice: Literal[1, 2, 3] = 2,
                  colour: Literal["red", "blue"] = "blue",
                  offset: tuple[float, float] = (1.0, -1.0), size: tuple[int, int, int] = (1, 2, 3),
                  names: tuple[str, str] = ("a", "b")) -> Echo:
    """Echo every control.

    Args:
        bounded: a bounded float.
    """
    return Echo(np.array([bounded, free, small]), float(bounded + free + small))


def blank(*, count: Annotated[int, Range(1, 4)] = 2) -> Loaded:
    return Loaded({"images": ImageSet(tuple(Image(np.zeros((4, 4), np.float32)) for _ in range(count)))})


EVERY = Pipeline.build(name="every", title="Every control", summary="",
                       steps=[every_control], datasets=[blank])


def test_widget_kinds_follow_the_control_schema():
    kinds = {c.name: widget_kind(c) for c in EVERY.step("every_control").controls}
    assert kinds == {"flag": "checkbox", "label": "text", "bounded": "slider",
                     "free": "number", "small": "slider",
                     "big": "number", "unbounded_int": "number", "choice": "dropdown", "colour": "dropdown",
                     "offset": "vector2", "size": "vector3", "names": "text"}


def test_widgets_show_defaults_ranges_and_round_trip_through_the_schema(server, store):
    view = make_view(server, store, {"every": EVERY})
    view.start({})
    row = view.rows["every_control"]
    handles = row.controls
    assert isinstance(handles["flag"], viser.GuiCheckboxHandle) and handles["flag"].value is True
    slider = handles["bounded"]
    assert isinstance(slider, viser.GuiSliderHandle)
    assert (slider.min, slider.max, slider.value, slider.step) == (0.1, 10.0, 1.0, 0.01)
    assert "a bounded float" in slider.hint and "range [0.1, 10]" in slider.hint
    assert isinstance(handles["small"], viser.GuiSliderHandle) and handles["small"].step == 1
    assert isinstance(handles["big"], viser.GuiNumberHandle) and (handles["big"].min,
                                                                  handles["big"].max) == (0, 100000)
    assert isinstance(handles["choice"], viser.GuiDropdownHandle)
    assert handles["choice"].options == ("1", "2", "3")
    assert handles["colour"].value == "blue"
    assert isinstance(handles["offset"], viser.GuiVector2Handle) and handles["offset"].value == (1.0, -1.0)
    assert isinstance(handles["size"], viser.GuiVector3Handle)
    assert handles["names"].value == "a, b"
    # the widgets' values, checked by the step's own schema, are exactly the defaults
    spec = EVERY.step("every_control")
    defaults = {c.name: c.default for c in spec.controls}
    assert spec.coerce_controls(view.step_params("every_control")) == defaults
    # and edits come through typed
    handles["choice"].value = "3"
    handles["size"].value = (4.0, 5.0, 6.0)
    handles["names"].value = "x, y"
    coerced = spec.coerce_controls(view.step_params("every_control"))
    assert coerced["choice"] == 3 and coerced["size"] == (4, 5, 6) and coerced["names"] == ("x", "y")


def test_toy_steps_are_listed_in_order_with_status(view):
    labels = [row.folder.label for row in view.rows.values()]
    assert labels == ["1. Add noise › ready", "2. Mean intensity · blocked", "3. Lift · blocked"]
    row = view.rows["add_noise"]
    assert row.buttons.options == ("Run", "Run to here", "Reset")
    assert (row.controls["sigma"].min, row.controls["sigma"].max,
            row.controls["sigma"].value) == (0.0, 1.0, 0.1)
    assert row.controls["mode"].options == ("gaussian", "uniform")
    assert isinstance(view.rows["lift"].controls["iterations"], viser.GuiSliderHandle)


def test_dataset_picker_offers_the_module_datasets_and_options(server, store, view):
    assert view.tab.module_dropdown.options == ("toy",)
    assert view.tab.dataset_dropdown.value == "gradients"
    count = view._dataset_option_handles["count"]
    assert (count.min, count.max, count.value) == (1, 8, 3)
    count.value = 2
    first = view.session
    view.new_session_from_gui()
    assert view.session is not first and len(view.session.get("images")) == 2
    assert view.session.options == {"count": 2}
    assert view.tab.session_id_text.value == view.session.id


def test_run_draws_outputs_and_shows_metrics(server, view):
    view.rows["add_noise"].controls["sigma"].value = 0.3
    view.press("add_noise", "Run")
    session = view.session
    record = session.history[-1]
    assert (record.step, record.status, record.params["sigma"]) == ("add_noise", "ok", 0.3)
    assert view.rows["add_noise"].folder.label == "1. Add noise ✓ done"
    assert view.rows["mean_intensity"].folder.label == "2. Mean intensity › ready"
    assert "mean_abs_change" in view.rows["add_noise"].metrics.content
    assert "intensity" in view.rows["add_noise"].metrics.content  # the metric's unit
    assert "noisy" in view.drawer.drawn and "images" in view.drawer.drawn
    assert "add_noise" in view.tab.history_md.content
    assert view.tab.media_panel.visible


def test_run_to_here_runs_missing_steps_with_progress(server, view):
    view.rows["lift"].controls["iterations"].value = 12
    view.press("lift", "Run to here")
    session = view.session
    assert [r.step for r in session.history] == ["add_noise", "mean_intensity", "lift"]
    assert session.history[-1].params == {"iterations": 12}
    assert "means_abs_error (evaluation)" in view.rows["mean_intensity"].metrics.content
    # the loss of every iteration was plotted, the bar reached 100 %
    progress = view.rows["lift"].progress  # in the step's own folder
    assert progress is not None and progress.text.visible and progress.loss_plot.visible
    assert list(progress.loss_plot.data[0]) == list(range(1, 13))
    assert progress.loss_plot.data[1][-1] == pytest.approx(0.5 ** 12)
    assert progress.bar.value == pytest.approx(100.0)
    assert progress.text.content.startswith("**lift**: iteration 12/12")
    assert "**ok**" in progress.text.content
    assert view.tab.cancel_button.disabled and progress.cancel.disabled  # nothing left to cancel
    assert isinstance(server.scene.get_handle_by_name("/lab/cloud"), viser.PointCloudHandle)


def test_progress_of_a_long_step_run_over_rest_is_shown(view):
    session = view.session
    session.run_until("mean_intensity")
    session.run("lift", {"iterations": 5})  # a script's run: the view listens to the session
    view.poll()
    progress = view.rows["lift"].progress
    assert progress is not None and progress.text.visible and list(progress.loss_plot.data[0]) == [1, 2, 3, 4, 5]
    assert "**ok**" in progress.text.content and view.rows["lift"].folder.label == "3. Lift ✓ done"


def test_reset_removes_outputs_and_drawings(server, view):
    view.press("lift", "Run to here")
    view.press("mean_intensity", "Reset")
    assert "means" not in view.session.state and "cloud" not in view.session.state
    assert server.scene.get_handle_by_name("/lab/cloud") is None
    assert "cloud" not in view.drawer.drawn
    assert view.rows["mean_intensity"].folder.label == "2. Mean intensity › ready"
    assert view.rows["lift"].metrics.content == ""


def test_errors_are_shown_never_raised(view):
    view.press("mean_intensity", "Run")  # its input does not exist yet
    assert view.tab.error_box.visible and "missing_input" in view.tab.error_box.content
    assert view.session.history == []
    view.rows["add_noise"].controls["mode"].value = "bogus"  # a value the dropdown never offers
    view.press("add_noise", "Run")
    assert "invalid_control" in view.tab.error_box.content and "mode" in view.tab.error_box.content
    view.guard(lambda: view.open_session_id("nope"))
    assert "not_found" in view.tab.error_box.content
    view.rows["add_noise"].controls["mode"].value = "uniform"
    view.press("add_noise", "Run")  # a good run clears the error
    assert not view.tab.error_box.visible and view.session.history[-1].status == "ok"


def test_a_step_that_fails_is_shown_with_its_reason(server, store):
    def explode(images: ImageSet) -> Annotated[np.ndarray, "boom"]:
        """Always fails."""
        raise RuntimeError("no board found")

    pipeline = Pipeline.build(name="bad", title="Bad", summary="", steps=[explode], datasets=[blank])
    view = make_view(server, store, {"bad": pipeline})
    view.start({})
    view.press("explode", "Run")
    assert "step_failed" in view.tab.error_box.content and "no board found" in view.tab.error_box.content
    assert "failed" in view.rows["explode"].metrics.content


def test_a_failed_step_reads_failed_until_it_runs_or_is_reset(server, store):
    def fragile(images: ImageSet, *, works: bool = False) -> Annotated[np.ndarray, "piece"]:
        """Fails unless told it works."""
        if not works:
            raise RuntimeError("the density never crosses the level")
        return np.zeros(3)

    pipeline = Pipeline.build(name="fragile", title="Fragile", summary="", steps=[fragile], datasets=[blank])
    view = make_view(server, store, {"fragile": pipeline})
    view.start({})
    row = view.rows["fragile"]
    assert row.folder.label == "1. Fragile › ready"
    view.run_all()  # Run all stops at the failure: the step says so, not "ready", even folded
    assert row.folder.label == "1. Fragile ✗ failed: see the error at the top"
    assert "the density never crosses" in view.tab.error_box.content
    row.controls["works"].value = True  # a changed control does not hide the failure
    assert row.folder.label.endswith("✗ failed: see the error at the top")
    view.press("fragile", "Reset")
    assert row.folder.label == "1. Fragile › ready"
    row.controls["works"].value = False
    with pytest.raises(Exception, match="density"):
        view.session.run("fragile")  # over REST, behind the viewer's back
    view.poll()
    assert row.folder.label.endswith("✗ failed: see the error at the top")
    row.controls["works"].value = True
    view.press("fragile", "Run")
    assert row.folder.label == "1. Fragile ✓ done" and not view.tab.error_box.visible


def test_changes_made_over_rest_are_redrawn_on_poll(server, store, view):
    session = view.session
    session.run("add_noise", {"sigma": 0.2})  # what a REST call does, behind the viewer's back
    assert view.rows["add_noise"].folder.label.endswith("ready")
    view.poll()
    assert view.rows["add_noise"].folder.label == "1. Add noise ✓ done"
    assert "noisy" in view.drawer.drawn
    drawn = view.drawer.drawn["noisy"]
    view.poll()  # nothing changed: nothing redrawn
    assert view.drawer.drawn["noisy"] is drawn
    store.delete(session.id)
    view.poll()
    assert f"session {session.id!r} was deleted; press New session" in view.tab.error_box.content


def test_a_full_store_is_shown_as_a_message_and_evicts_nobody(server):
    store = SessionStore(max_sessions=1)
    kept = store.create(TOY)
    view = make_view(server, store)
    view.start({})  # no room for the tab's own session: say so, open nothing, keep the other one
    assert "overloaded" in view.tab.error_box.content and "limit 1" in view.tab.error_box.content
    assert view.session is None and store.ids() == [kept.id]
    view.guard(view.new_session_from_gui)
    assert "retry later" in view.tab.error_box.content and store.ids() == [kept.id]
    view.poll()  # a tab without a session polls quietly


def test_opening_a_session_by_id(server, store, view):
    other = store.create(TOY, options={"count": 1})
    other.run("add_noise")
    view.tab.session_id_text.value = other.id
    view.guard(lambda: view.open_session_id(view.tab.session_id_text.value))
    assert view.session is other
    assert other.id in view.tab.header.content
    assert view.rows["add_noise"].folder.label == "1. Add noise ✓ done"
    assert "noisy" in view.drawer.drawn


def test_start_opens_the_session_of_the_query(server, store):
    made = store.create(TOY)
    view = make_view(server, store)
    view.start({"session": made.id})
    assert view.session is made and len(store) == 1
    missing = make_view(server, store)
    missing.start({"session": "gone"})  # an unknown id: say so, and open a fresh session instead
    assert "not_found" in missing.tab.error_box.content and missing.session is not None and len(store) == 2


def slow(images: ImageSet, *, iterations: Annotated[int, Range(1, 100000)] = 100000
         ) -> Generator[Progress, None, Annotated[np.ndarray, "result"]]:
    """A long step that only ends when cancelled."""
    for i in range(iterations):
        time.sleep(0.001)
        yield Progress(iteration=i + 1, total=iterations, loss=1.0 / (i + 1))
    return np.zeros(1)


SLOW = Pipeline.build(name="slow", title="Slow", summary="", steps=[slow], datasets=[blank])


def test_long_step_runs_in_background_and_cancels(server, store):
    view = make_view(server, store, {"slow": SLOW}, background=True)
    view.start({})
    view.press("slow", "Run")
    deadline = time.monotonic() + 30
    while view.progress.state.iteration < 1 and view.worker.is_alive() and time.monotonic() < deadline:
        time.sleep(0.01)  # until the first progress snapshot is on screen
    view.guard(lambda: view.press("slow", "Run"))  # a second run while one is going: refused
    assert "still running" in view.tab.error_box.content
    view.guard(view.cancel)
    view.wait(30)
    assert not view.worker.is_alive()
    assert view.session.history[-1].status == "cancelled"
    assert "cancelled" in view.tab.error_box.content and "**cancelled**" in view.rows["slow"].progress.text.content
    assert view.rows["slow"].folder.label.endswith("ready")


def test_formatting_helpers():
    assert nice_step(1.0) == 0.01 and nice_step(9.9) == 0.01 and nice_step(1000) == 10
    assert nice_step(1.0, 0.0, 0.025) == pytest.approx(0.001)  # the default 0.025 lies on a step
    assert format_number(0.123456) == "0.1235" and format_number(3) == "3" and format_number(True) == "yes"
    assert format_number(1e-7) == "1.000e-07"
    assert format_number([0.1, 0.5, 0.2, 0.3, 0.9]) == "5 values, max 0.9"
    text = metrics_markdown(TOY.step("add_noise"), {"mean_abs_change": 0.5, "extra": 1}, ["view 3: no board"])
    assert "| mean_abs_change | 0.5 intensity |" in text
    assert "extra (evaluation)" in text
    assert "⚠ view 3" in text


def test_add_control_widget_for_a_required_number(server):
    from lab.core.step import Control

    control = Control("tolerance", "float", None, minimum=0.5, required=True)
    handle = add_control_widget(server.gui, control)
    assert isinstance(handle, viser.GuiNumberHandle) and handle.value == 0.5
    assert widget_value(control, handle) == 0.5


@step_result
class Grown:
    final: np.ndarray
    points: int = metric("points grown")


def grow(images: ImageSet, *, steps: Annotated[int, Range(1, 10)] = 3) -> Generator[Progress, None, Grown]:
    """A long step that shows a preview point cloud while it runs."""
    from lab.core import PointCloud

    for i in range(steps):
        yield Progress(iteration=i + 1, total=steps, loss=1.0 / (i + 1),
                       values={"preview_cloud": PointCloud(np.zeros((i + 1, 3)))})
    return Grown(np.zeros(steps), steps)


GROW = Pipeline.build(name="grow", title="Grow", summary="", steps=[grow], datasets=[blank])


def test_preview_values_of_a_long_step_are_drawn_while_it_runs(server, store):
    view = make_view(server, store, {"grow": GROW})
    view.start({})
    seen = []
    view.session.listeners.append(
        lambda step, progress: seen.append(server.scene.get_handle_by_name("/lab/preview_cloud") is not None))
    view.press("grow", "Run")
    assert seen and seen[0]  # drawn at the first snapshot (the view listens before this test does)
    assert server.scene.get_handle_by_name("/lab/preview_cloud") is None  # gone once the real state is drawn
    assert view.session.history[-1].status == "ok"


def test_a_session_of_a_module_not_offered_here_still_opens(server, store):
    view = make_view(server, store, {"every": EVERY})
    view.start({})
    toy = store.create(TOY)
    view.open_session_id(toy.id)
    assert view.tab.module_dropdown.value == "toy" and "toy" in view.tab.module_dropdown.options
    assert view.tab.dataset_dropdown.value == "gradients"
    assert list(view.rows) == ["add_noise", "mean_intensity", "lift"]


def test_export_of_a_session():
    from lab.core import open_session
    from lab.viewer import export_scene_html

    session = open_session(TOY, options={"count": 2, "size": 8})
    session.run_until("lift")
    html = export_scene_html(session)
    assert "__VISER_EMBED_DATA__" in html and len(html) > 100_000  # the whole client is inlined
