"""Splatting's interaction: a click on a held-out view's picture runs render_view for that pixel, so the
chart and the 3D points list the Gaussians it is made of; clicks elsewhere, or before a model, select the
view as usual."""

from __future__ import annotations

import time

import numpy as np
import torch

from lab.viewer.interactions.splatting import PixelGaussians, clicked_pixel

torch.set_num_threads(1)

LIGHT = {"initialize_gaussians": {"points": 200},
         "train_splats": {"iterations": 10, "budget_seconds": 0.0, "densify_every": 0, "preview_every": 10}}


def test_a_click_position_is_the_pixel_that_holds_it():
    assert clicked_pixel(np.array([50.3, 40.7]), 100, 80) == (50, 40)
    assert clicked_pixel(np.array([100.0, 80.0]), 100, 80) == (99, 79)   # the far edges: the last pixel
    assert clicked_pixel(np.array([-0.2, 0.0]), 100, 80) == (0, 0)


def test_a_click_on_a_held_out_picture_lists_that_pixels_gaussians(server, store):
    from lab.modules import get_pipeline
    from lab.viewer.app import ClientView, ModuleCatalog

    pipeline = get_pipeline("splatting")
    session = store.create(pipeline, "synthetic_object", {"train_views": 2, "test_views": 2})
    view = ClientView(server, store, ModuleCatalog([pipeline]), is_client=False, background=False)
    try:
        view.open_session(session)
        explorer = next(i for i in view.interactions if isinstance(i, PixelGaussians))
        assert not view._pixel_clicked("test_renders", 1, np.array([50.3, 40.7]))  # nothing trained yet
        session.run_until("render_held_out", LIGHT)
        assert view._pixel_clicked("test_renders", 1, np.array([50.3, 40.7]))
        assert explorer.last == (1, 50, 40)
        deadline = time.monotonic() + 60
        while "pixel_gaussians" not in session.state and time.monotonic() < deadline:
            time.sleep(0.05)
        record = [r for r in session.history if r.step == "render_view"][-1]
        assert record.params["view"] == 1 and (record.params["pixel_u"], record.params["pixel_v"]) == (50, 40)
        assert "pixel (50, 40)" in session.state["pixel_gaussians"].title
        assert not view._pixel_clicked("images", 0, np.array([5.0, 5.0]))  # the training views: select
    finally:
        view.close()
