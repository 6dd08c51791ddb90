"""The hook for module-specific interactions: found by the pipeline's name, built in a folder of
their own when a session opens, updated after every redraw, closed when the tab shows another
session; a failing interaction is shown in the tab and never breaks it."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import pytest

import lab.viewer.view as viewer_view
from lab.core.errors import InvalidValue
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.interactions import EXPLORE_ROOT, Interaction, interactions_for
from toy_pipeline import TOY


class Recorder(Interaction):
    """Draws a marker at the mean of ``cloud`` and counts updates."""

    title = "Recorder"
    made: ClassVar[list[Recorder]] = []

    def __init__(self, ctx):
        super().__init__(ctx)
        self.updates: list[set[str]] = []
        self.closed = False
        self.button = self.track(ctx.gui.add_button("poke"))
        self.marker = None
        Recorder.made.append(self)

    def update(self, state):
        self.updates.append(set(state))
        if "cloud" in state and self.marker is None:
            centre = state["cloud"].xyz.mean(axis=0)
            self.marker = self.track(self.ctx.scene.add_icosphere(self.ctx.node("centre"), radius=0.1,
                                                                  position=tuple(centre)))

    def poke(self, value: float):
        if value < 0:
            raise InvalidValue("value", "must be at least 0")
        self.ctx.run("add_noise", {"sigma": value})

    def close(self):
        self.closed = True
        super().close()


class Boxed(Interaction):
    def bounds(self):
        return np.array([[0.0, 0.0, 0.0], [2.0, 2.0, 2.0]])


class Broken(Interaction):
    def __init__(self, ctx):
        raise RuntimeError("broken on purpose")


@pytest.fixture
def view(server, store, monkeypatch):
    Recorder.made.clear()
    monkeypatch.setattr(viewer_view, "interactions_for", lambda name: [Recorder] if name == "toy" else [])
    view = ClientView(server, store, ModuleCatalog({"toy": TOY}), is_client=False, background=False)
    view.start({})
    return view


def test_modules_without_an_interactions_file_have_none():
    assert interactions_for("toy") == []
    assert interactions_for("no_such_module") == []


def test_interaction_is_built_updated_and_closed(view, store):
    [recorder] = view.interactions
    assert recorder.ctx.session is view.session
    assert recorder.updates and "images" in recorder.updates[-1]
    view.run("lift", until=True)
    assert "cloud" in recorder.updates[-1]
    assert recorder.marker is not None
    assert recorder.ctx.node("centre") == f"{EXPLORE_ROOT}/toy/centre"
    assert recorder.ctx.extent() > 0
    view.open_session(store.create(TOY))
    assert recorder.closed and recorder.handles == []
    assert len(view.interactions) == 1 and view.interactions[0] is not recorder


def test_interaction_runs_steps_and_errors_are_shown(view):
    [recorder] = view.interactions
    recorder.poke(0.5)
    assert view.session.step_status()["add_noise"] == "done"
    recorder.ctx.guarded(recorder.poke)(-1.0)
    assert "must be at least 0" in view.errors[-1]


def test_restart_keeps_module_and_dataset_and_changes_options(view):
    old = view.session
    view.interactions[0].ctx.restart({"count": 2})
    assert view.session is not old
    assert view.session.options["count"] == 2 and view.session.dataset == old.dataset
    assert len(view.session.state["images"].images) == 2


def test_a_broken_interaction_is_shown_not_raised(server, store, monkeypatch):
    monkeypatch.setattr(viewer_view, "interactions_for", lambda name: [Broken, Recorder])
    view = ClientView(server, store, ModuleCatalog({"toy": TOY}), is_client=False, background=False)
    view.start({})
    assert any("broken on purpose" in e for e in view.errors)
    assert [type(i) for i in view.interactions] == [Recorder]
    assert np.isfinite(view.interactions[0].ctx.extent())


def test_the_tab_frames_what_interactions_draw_when_the_state_has_no_3d_values(server, store, monkeypatch):
    monkeypatch.setattr(viewer_view, "interactions_for", lambda name: [Recorder, Boxed])
    view = ClientView(server, store, ModuleCatalog({"toy": TOY}), is_client=False, background=False)
    view.start({})
    from lab.viewer.camera import CameraPose, Viewport, box_corners, project

    def seen(points, framed):  # inside the default canvas (viser's fov, the canvas between the panels)
        eye, look_at = framed
        pose = CameraPose(np.asarray(eye), np.asarray(look_at), np.array([0.0, -1.0, 0.0]))
        xy = project(points, pose, Viewport())
        return bool(np.all((xy > 0.0) & (xy < 1.0)))

    box = box_corners(np.array([[0.0, 0.0, 0.0], [2.0, 2.0, 2.0]]))
    framed = view.framing(dict(view.session.state))
    assert framed is not None and seen(box, framed)
    np.testing.assert_allclose(framed[1], [1.0, 1.0, 1.0], atol=0.5)  # it orbits about the box's middle
    view.run("lift", until=True)
    cloud = view.session.state["cloud"]
    framed = view.framing(dict(view.session.state))
    assert seen(cloud.xyz, framed) and seen(box, framed)  # the state's values and what interactions draw


def test_restart_runs_to_a_step_with_params_and_carries_to_the_new_interactions(view):
    old = view.interactions[0]
    assert old.ctx.restart({"count": 3}, run_to="mean_intensity",
                           params=lambda fresh: {"add_noise": {
                               "sigma": 0.0 if len(fresh.state["images"]) == 3 else 1.0}},
                           carry={"note": "from the old tab"})
    view.wait()
    session = view.session
    assert session.step_status()["mean_intensity"] == "done" and session.step_status()["lift"] == "ready"
    [noise] = [r for r in session.history if r.step == "add_noise"]
    assert noise.params["sigma"] == 0.0
    assert view.interactions[0].ctx.carried == {"note": "from the old tab"}
    # out of range: shown, session kept
    assert not old.ctx.restart({"count": 99}) and "count" in view.errors[-1]
    assert view.session is session and view.interactions[0].ctx.carried == {"note": "from the old tab"}
    assert not view.interactions[0].ctx.restart({}, run_to="no_such_step") and view.session is session
