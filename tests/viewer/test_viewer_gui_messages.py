"""The GUI messages the viewer sends, as viser's browser client takes them (issue 16: "Tried to update
non-existent component" in the console).

viser's client handles a frame's messages in order, but defers the frame's GUI *updates* until after its adds
and removes: an element updated and then removed within one frame gets its update after its removal, and the
console logs the error. viser's ``add_image`` itself is an add and then an update (the picture travels as an
update), so a picture removed and added again for every new value, or a chart replaced when its shape
changes, does it whenever two refreshes reach a slow page within one frame (software WebGL draws a frame in
hundreds of ms). So the viewer changes its GUI pictures and charts in place and removes an element only when
its value is gone: here every GUI message is recorded as the server queues it, and a run of a pipeline must
update no element it removes, every picture and chart keeping its element from the first value to the last.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from dataclasses import dataclass, field

import numpy as np
import pytest
import viser

from lab.core import Curve, Image, ImageSet, Loaded, Pipeline, Points2D, Progress
from lab.core.step import step_result
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.plots import set_uplot
from lab.viewer import renderers
from lab.viewer.renderers import Canvas, StateDrawer


@dataclass
class GuiMessages:
    """The GUI messages a server queued, in order: ``(phase, uuid, updated keys)`` with phase ``create``,
    ``update_dict`` or ``remove`` (what viser's client sees, before the server's buffer drops the updates of
    an element removed before they were sent: these checks assume they were sent)."""

    log: list[tuple[str, str, tuple[str, ...]]] = field(default_factory=list)

    def mark(self) -> int:
        return len(self.log)

    def created(self, since: int = 0) -> list[str]:
        return [uuid for phase, uuid, _ in self.log[since:] if phase == "create"]

    def removed(self, since: int = 0) -> list[str]:
        return [uuid for phase, uuid, _ in self.log[since:] if phase == "remove"]

    def updates(self, uuid: str, since: int = 0) -> list[tuple[str, ...]]:
        return [keys for phase, u, keys in self.log[since:] if phase == "update_dict" and u == uuid]

    def updated_then_removed(self, since: int = 0) -> list[str]:
        """Elements updated and later removed (from ``since`` on): each would be an error in the console
        when both messages reach the page within one frame."""
        updated: set[str] = set()
        hazards = []
        for phase, uuid, _ in self.log[since:]:
            if phase == "update_dict":
                updated.add(uuid)
            elif phase == "remove" and uuid in updated:
                hazards.append(uuid)
        return hazards

    def updates_of_the_removed(self) -> list[str]:
        """Elements updated after their removal (always an error in the console)."""
        gone: set[str] = set()
        late = []
        for phase, uuid, _ in self.log:
            if phase == "remove":
                gone.add(uuid)
            elif phase == "update_dict" and uuid in gone:
                late.append(uuid)
        return late


@pytest.fixture
def gui_messages(server) -> GuiMessages:
    """Every GUI message ``server`` queues from now on."""
    messages = GuiMessages()
    interface = server.gui._websock_interface
    queue = interface.queue_message

    def spy(message):
        if getattr(message, "entity_type", None) == "gui" and message.lifecycle_phase is not None:
            keys = tuple(sorted(getattr(message, "updates", {}) or {}))
            messages.log.append((message.lifecycle_phase, message.uuid, keys))
        return queue(message)

    interface.queue_message = spy
    return messages


def elements(drawer: StateDrawer) -> dict[str, dict[str, str]]:
    """The uuid of each GUI element the drawer holds, by value name and part."""
    return {name: {part: h._impl.uuid for part, h in drawn.parts.items() if hasattr(h, "_impl")}
            for name, drawn in drawer.drawn.items()}


def gray(value: float, name: str = "", size: tuple[int, int] = (20, 30)) -> Image:
    return Image(np.full(size, value, np.float32), name)


@pytest.fixture(autouse=True)
def removed_at_once(monkeypatch):
    """A removal's messages without the settling time of a picture just drawn (tested alone below)."""
    monkeypatch.setattr(renderers, "GUI_SETTLE_S", 0.0)


# --- the drawer: a new value changes its element ----------------------------------------------------------
def test_new_values_change_the_pictures_and_charts_in_place(server, gui_messages):
    drawer = StateDrawer(Canvas(scene=server.scene, gui=server.gui))
    views = ImageSet((gray(0.0, "a"), gray(1.0, "b")))

    def state(k: int) -> dict:
        return {"photo": gray(k / 4, size=(20 + k, 30)), "views": views,
                "corners": Points2D(np.full((k + 1, 2), 5.0), image="views"),
                "loss": Curve(np.arange(k + 3.0), np.linspace(1.0, 0.1, k + 3)[None].repeat(1 + k % 2, 0)),
                "rms": Curve(np.arange(3.0), np.array([0.1, 0.3, 0.2]) * (k + 1), kind="bar")}

    drawer.sync(state(0))
    first = gui_messages.mark()
    made = elements(drawer)
    for k in range(1, 4):  # four runs: a new photo, overlays, a longer loss with more series, new bars
        assert sorted(drawer.sync(state(k))) == ["loss", "photo", "rms", "views"]
    assert gui_messages.created(first) == [] and gui_messages.removed(first) == []
    assert elements(drawer) == made  # the same elements
    parts = {name: drawn.parts for name, drawn in drawer.drawn.items()}
    photo, picture, chart = parts["photo"]["image"], parts["views"]["image"], parts["loss"]["chart"]
    assert ("_data",) in gui_messages.updates(made["photo"]["image"], first)
    assert photo.label == "photo (30x23)"
    assert ("_data",) in gui_messages.updates(made["rms"]["chart"], first)
    assert "corners: 4" in picture.label  # the overlays changed: the view is drawn again
    assert {("data",), ("series",)} <= set(gui_messages.updates(made["loss"]["chart"], first))
    assert len(chart.data) == 3 and len(chart.data[0]) == 6  # x and two series of 6 points


def test_a_curve_turned_into_bars_and_back_hides_an_element_and_removes_none(server, gui_messages):
    drawer = StateDrawer(Canvas(scene=server.scene, gui=server.gui))
    drawer.sync({"c": Curve(np.arange(4.0), np.arange(4.0))})
    line = drawer.drawn["c"].parts["chart"]
    assert isinstance(line, viser.GuiUplotHandle) and line.visible
    drawer.sync({"c": Curve(np.arange(4.0), np.arange(4.0) + 1.0)})  # a preview updates the chart, then
    drawer.sync({"c": Curve(np.arange(4.0), np.arange(4.0), kind="bar")})  # the result is a bar chart
    bars = drawer.drawn["c"].parts["chart"]
    assert isinstance(bars, viser.GuiImageHandle) and bars.visible and not line.visible
    drawer.sync({"c": Curve(np.arange(5.0), np.arange(5.0))})  # a line again: the same chart, shown
    assert drawer.drawn["c"].parts["chart"] is line and line.visible and not bars.visible
    assert len(line.data[0]) == 5
    assert gui_messages.removed() == [] and gui_messages.created() == [line._impl.uuid, bars._impl.uuid]
    drawer.sync({})  # the value gone: both go, neither updated after
    assert sorted(gui_messages.removed()) == sorted([line._impl.uuid, bars._impl.uuid])
    assert gui_messages.updates_of_the_removed() == []


def test_a_value_gone_is_removed_once_and_never_updated_after(server, gui_messages):
    drawer = StateDrawer(Canvas(scene=server.scene, gui=server.gui))
    drawer.sync({"views": ImageSet((gray(0.0), gray(1.0))), "photo": gray(0.5)})
    drawer.sync({})  # a re-run upstream dropped them
    assert drawer.drawn == {}
    drawer.show_view("views", 1)  # a late click on a frustum of the image set gone
    drawer.sync({})
    assert gui_messages.updates_of_the_removed() == []
    assert len(gui_messages.removed()) == len(set(gui_messages.removed()))


def test_a_picture_removed_just_after_its_drawing_is_hidden_then_removed_never_updated_after(
        server, gui_messages, monkeypatch):
    # longer than a slow page's frame, and than a cold first drawing takes (the photo must still be young)
    monkeypatch.setattr(renderers, "GUI_SETTLE_S", 2.0)
    drawer = StateDrawer(Canvas(scene=server.scene, gui=server.gui))
    drawer.sync({"photo": gray(0.5), "views": ImageSet((gray(0.0), gray(1.0)))})
    photo = drawer.drawn["photo"].parts["image"]
    start = gui_messages.mark()
    drawer.sync({})  # dropped within a frame of its drawing (splatting's render steps end milliseconds apart)
    assert gui_messages.removed(start) == [] and not photo.visible  # hidden at once, still there
    deadline = time.monotonic() + 10
    while photo._impl.uuid not in gui_messages.removed(start) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert photo._impl.uuid in gui_messages.removed(start)
    removed = gui_messages.removed(start)
    assert len(removed) == len(set(removed)) == 4  # the photo, the folder, its slider and its picture
    assert gui_messages.updates_of_the_removed() == []


def test_set_uplot_sends_what_changed_never_a_series_without_its_data(server, gui_messages):
    x = np.arange(5.0)
    plot = server.gui.add_uplot((x, x), ({"label": "x"}, {"label": "a"}))
    start = gui_messages.mark()
    set_uplot(plot, data=(x, x), series=({"label": "x"}, {"label": "a"}), title=None)
    assert gui_messages.updates(plot._impl.uuid, start) == []  # nothing changed: nothing sent
    set_uplot(plot, data=(x, x, x), series=({"label": "x"}, {"label": "a"}, {"label": "b"}))
    assert gui_messages.updates(plot._impl.uuid, start) == [("data",), ("series",)]  # grows: data first
    start = gui_messages.mark()
    set_uplot(plot, data=(x, x), series=({"label": "x"}, {"label": "a"}), title="fewer")
    assert gui_messages.updates(plot._impl.uuid, start) == [("series",), ("data",), ("title",)]
    with pytest.raises(TypeError, match="legend"):
        set_uplot(plot, legend={"live": False})


# --- a tab running a pipeline ------------------------------------------------------------------------------
@step_result
class Developed:
    photo: Image
    histogram: Curve


@step_result
class Painted:
    canvas: Image
    loss: Curve


@step_result
class Marked:
    marks: Points2D


def develop(views: ImageSet, *, gain: float = 1.0) -> Developed:
    """A picture and a bar chart."""
    bars = Curve(np.arange(3.0), np.array([1.0, 2.0, gain]), kind="bar")
    return Developed(gray(min(gain * 0.5, 1.0)), bars)


def paint(photo: Image) -> Generator[Progress, None, Painted]:
    """A long step whose snapshots carry a picture (texture's quilt as it grows) and a loss."""
    for i in range(1, 6):
        yield Progress(i, 5, 1.0 / i, values={"canvas": gray(i / 5, size=(10 + i, 10))})
    return Painted(gray(1.0), Curve(np.arange(5.0), 1.0 / np.arange(1.0, 6.0)))


def mark(views: ImageSet, canvas: Image) -> Marked:
    """Overlays on the image set (redrawn into its picture)."""
    return Marked(Points2D(np.array([[3.0, 4.0], [5.0, 6.0]]), view=np.array([0, 1]), image="views"))


def two_views() -> Loaded:
    return Loaded({"views": ImageSet((gray(0.2, "left"), gray(0.8, "right")))})


PICTURES = Pipeline.build(name="pictures", title="Pictures", summary="", steps=[develop, paint, mark],
                          datasets=[two_views])


def test_running_a_pipeline_updates_no_element_it_removes(server, store, gui_messages):
    view = ClientView(server, store, ModuleCatalog({"pictures": PICTURES}), is_client=False, background=False)
    view.start({})
    run = gui_messages.mark()
    view.run_all()
    assert [r.status for r in view.session.history] == ["ok"] * 3
    made = elements(view.drawer)
    assert set(made) == {"views", "photo", "histogram", "canvas", "loss"}
    assert gui_messages.updated_then_removed(run) == []
    again = gui_messages.mark()
    view.press("develop", "Run")  # re-run with its dependants: every value new, every element the same
    assert [r.status for r in view.session.history[-3:]] == ["ok"] * 3
    assert elements(view.drawer) == made
    assert gui_messages.updated_then_removed(run) == [] and gui_messages.removed(again) == []
    view.reset("paint")  # the user resets: what paint and mark wrote goes, and is never updated after
    assert set(view.drawer.drawn) == {"views", "photo", "histogram"}
    view.drawer.show_view("views", 1)
    assert gui_messages.updates_of_the_removed() == []


def test_the_loss_plot_of_a_long_step_keeps_its_element_across_runs(server, store, gui_messages):
    view = ClientView(server, store, ModuleCatalog({"pictures": PICTURES}), is_client=False, background=False)
    view.start({})
    plot = view.tab.steps_folder.progress["paint"].loss_plot
    view.run_all()
    view.reset("develop")
    view.run_all()
    uuid = plot._impl.uuid
    assert uuid not in gui_messages.removed() and ("data",) in gui_messages.updates(uuid)
    assert len(plot.data[0]) == 5  # the second run's losses only
    assert gui_messages.updates_of_the_removed() == []


def test_a_new_session_of_the_module_keeps_the_elements_of_its_names(server, store, gui_messages):
    view = ClientView(server, store, ModuleCatalog({"pictures": PICTURES}), is_client=False, background=False)
    view.start({})
    view.run_all()
    made = elements(view.drawer)
    start = gui_messages.mark()
    view.open_session(store.create(PICTURES))  # "New session": only the dataset's values so far
    assert set(view.drawer.drawn) == {"views"} and elements(view.drawer)["views"] == made["views"]
    assert gui_messages.updated_then_removed(start) == []
    assert not {uuid for parts in made.values() for uuid in parts.values()} - {*made["views"].values()} - \
        {*gui_messages.removed(start)}  # the others went with their values


def test_a_name_drawn_as_another_type_is_drawn_anew(server, gui_messages):
    drawer = StateDrawer(Canvas(scene=server.scene, gui=server.gui))
    drawer.sync({"x": gray(0.5)})
    picture = elements(drawer)["x"]["image"]
    assert drawer.sync({"x": Curve(np.arange(4.0), np.arange(4.0))}) == ["x"] and drawer.errors == {}
    assert gui_messages.removed() == [picture] and "chart" in drawer.drawn["x"].parts
