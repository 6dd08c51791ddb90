"""The generic viewer draws what splatting's Run all leaves (light controls: a few hundred Gaussians, tens
of iterations, a few orbit frames): every typed value of the state has its renderer and draws without error
(the splats through viser's Gaussian splat renderer), the held-out and orbit cameras carry their pictures,
the legend names the splats and the pixel's Gaussians, and a tab opens on the session framing the scene."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from lab.core import Cameras, Curve, GaussianSplats, Image, ImageSet, PointCloud, SessionStore
from lab.modules import get_pipeline

torch.set_num_threads(1)

#: Controls that keep Run all to seconds on a shared CPU (the drawings do not change kind).
LIGHT = {"initialize_gaussians": {"points": 300},
         "train_splats": {"iterations": 30, "budget_seconds": 0.0, "densify_from": 10, "densify_every": 10,
                          "preview_every": 15},
         "render_path": {"frames": 3, "scale": 0.5}}


@pytest.fixture(scope="module")
def ran():
    store = SessionStore(max_sessions=2)
    pipeline = get_pipeline("splatting")
    session = store.create(pipeline, pipeline.datasets[0].name, {"train_views": 4, "test_views": 2})
    records = session.run_until(None, LIGHT)
    return store, session, records


def test_run_all_runs_every_step_with_light_controls(ran):
    _, session, records = ran
    assert [r.step for r in records] == [s.name for s in session.pipeline.steps]
    assert all(r.status == "ok" for r in records), [r.error for r in records]


def test_every_drawn_value_has_a_renderer_and_draws(ran, server):
    from lab.viewer.legend import legend_entries
    from lab.viewer.renderers import Canvas, StateDrawer, renderer_for

    _, session, _ = ran
    state = dict(session.state)
    kinds = {name: type(value) for name, value in state.items() if renderer_for(value) is not None}
    assert {"cameras": Cameras, "test_cameras": Cameras, "held_out_cameras": Cameras, "path_cameras": Cameras,
            "splats": GaussianSplats, "images": ImageSet,
            "test_renders": ImageSet, "path_frames": ImageSet, "preview": Image, "rendered": Image,
            "loss_curve": Curve, "psnr_curve": Curve, "density_curve": Curve, "pixel_gaussians": Curve,
            "pixel_splats": PointCloud}.items() <= kinds.items()
    drawer = StateDrawer(Canvas(scene=server.scene, gui=server.gui, images=server.gui.add_folder("images"),
                                plots=server.gui.add_folder("plots")))
    drawn = drawer.sync(state)
    assert drawer.errors == {} and set(kinds) <= set(drawn)
    for name in ("held_out_cameras", "path_cameras"):  # one frustum per camera, each carrying its view
        assert len(drawer.drawn[name].handles) == 1 + len(state[name])
    assert state["held_out_cameras"].image == "test_renders" and state["path_cameras"].image == "path_frames"
    named = {entry.name for entry in legend_entries(state)}
    assert {"splats", "pixel_splats"} <= named


def test_a_tab_opens_on_the_session_framing_the_splats(ran, server):
    from lab.viewer.app import ClientView, ModuleCatalog
    from lab.viewer.camera import DEFAULT_ASPECT, Viewport, aim, frame_pose

    store, session, _ = ran
    view = ClientView(server, store, ModuleCatalog([session.pipeline]), is_client=False, background=False)
    try:
        view.open_session(session)
        state = dict(session.state)
        assert frame_pose(state, view.interactions, Viewport(np.radians(75.0), DEFAULT_ASPECT)) is not None
        points, _ = aim(state, view.interactions)
        box = state["bounds"].center + state["bounds"].radius * np.array([[-1.0], [1.0]])
        assert np.all(points.min(axis=0) <= box[1]) and np.all(points.max(axis=0) >= box[0])
    finally:
        view.close()
