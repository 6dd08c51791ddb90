"""The generic viewer draws what NeRF's Run all leaves (light controls: a tiny grid, a short warm-up, a few
orbit frames): every typed value of the state has its renderer and draws without error, the training cameras
and the orbit carry their images on their frustums, and a browser tab's view opens on the session (framing,
legend) with the mesh and the cameras in it."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from lab.core import Cameras, Curve, Image, ImageSet, Mesh, SessionStore
from lab.modules import get_pipeline

torch.set_num_threads(1)

#: Controls that keep Run all to seconds on a shared CPU (the drawings do not change kind).
LIGHT = {"fit_image_2d": {"side": 24, "iterations": 20},
         "train_nerf": {"method": "grid", "grid_resolution": 32, "iterations": 120, "batch_rays": 512,
                        "budget_seconds": 0.0, "preview_every": 60},
         "render_path": {"frames": 4, "scale": 0.3},
         "extract_mesh": {"resolution": 32, "level": 2.0}}


@pytest.fixture(scope="module")
def ran():
    store = SessionStore(max_sessions=2)
    pipeline = get_pipeline("nerf")
    session = store.create(pipeline, pipeline.datasets[0].name, {"train_views": 6, "test_views": 2})
    records = session.run_until(None, LIGHT)
    return store, session, records


def test_run_all_runs_every_step_with_light_controls(ran):
    _, session, records = ran
    assert [r.step for r in records] == [s.name for s in session.pipeline.steps]
    assert all(r.status == "ok" for r in records)


def test_every_drawn_value_has_a_renderer_and_draws(ran, server):
    from lab.viewer.renderers import Canvas, StateDrawer, renderer_for

    _, session, _ = ran
    state = dict(session.state)
    kinds = {name: type(value) for name, value in state.items() if renderer_for(value) is not None}
    assert {"cameras": Cameras, "test_cameras": Cameras, "path_cameras": Cameras, "mesh": Mesh,
            "images": ImageSet, "path_frames": ImageSet, "fit_images": ImageSet, "test_renders": ImageSet,
            "preview": Image, "rendered": Image, "depth_map": Image, "opacity_map": Image,
            "fit_psnr": Curve, "loss_curve": Curve, "ray_weights": Curve}.items() <= kinds.items()
    drawer = StateDrawer(Canvas(scene=server.scene, gui=server.gui, images=server.gui.add_folder("images"),
                                plots=server.gui.add_folder("plots")))
    drawn = drawer.sync(state)
    assert drawer.errors == {} and set(kinds) <= set(drawn)
    for name in ("cameras", "path_cameras"):  # one frustum per camera, each carrying its view
        assert len(drawer.drawn[name].handles) == 1 + len(state[name])
    assert state["path_cameras"].image == "path_frames" and state["cameras"].image == "images"


def test_a_tab_opens_on_the_session_framing_the_scene(ran, server):
    from lab.viewer.app import ClientView, ModuleCatalog
    from lab.viewer.camera import DEFAULT_ASPECT, Viewport, aim, frame_pose

    store, session, _ = ran
    view = ClientView(server, store, ModuleCatalog([session.pipeline]), is_client=False, background=False)
    try:
        view.open_session(session)
        state = dict(session.state)
        pose = frame_pose(state, view.interactions, Viewport(np.radians(75.0), DEFAULT_ASPECT))
        assert pose is not None
        points, _ = aim(state, view.interactions)
        mesh = state["mesh"].vertices
        assert np.all(points.min(axis=0) <= mesh.min(axis=0) + 1e-9)  # the mesh is inside what is framed
        assert np.all(points.max(axis=0) >= mesh.max(axis=0) - 1e-9)
    finally:
        view.close()
