"""NeRF's ray click (issue 17, viewer): render_held_out's cameras carry the renders, render_view's ray_samples
are the clicked ray's samples in 3D (on that pixel's ray, coloured by weight), and in a viewer tab a click on
a held-out picture runs render_view for that pixel; clicks elsewhere, or before a model, select as usual."""

from __future__ import annotations

import time

import numpy as np
import torch

from lab.core import SessionStore
from lab.modules.nerf import PIPELINE
from lab.modules.nerf.steps import weight_colors
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.interactions.nerf import RayOfPixel
from lab.viewer.pixel_click import clicked_pixel

torch.set_num_threads(1)

LIGHT = {"train_nerf": {"method": "grid", "grid_resolution": 24, "iterations": 60, "batch_rays": 512,
                        "budget_seconds": 0.0, "preview_every": 60}}


def test_a_click_position_is_the_pixel_that_holds_it():
    assert clicked_pixel(np.array([50.3, 40.7]), 100, 80) == (50, 40)
    assert clicked_pixel(np.array([100.0, 80.0]), 100, 80) == (99, 79)
    assert clicked_pixel(np.array([-0.2, 0.0]), 100, 80) == (0, 0)


def test_weight_colours_grey_to_red():
    colours = weight_colors(np.array([0.0, 0.5, 2.0]))
    np.testing.assert_allclose(colours, [[0.6, 0.6, 0.6], [0.7, 0.45, 0.45], [1.0, 0.0, 0.0]])
    np.testing.assert_allclose(weight_colors(np.zeros(2)), 0.6)


def test_a_click_on_a_held_out_picture_shows_that_pixels_ray(server):
    store = SessionStore(max_sessions=2)
    session = store.create(PIPELINE, "synthetic_object", {"train_views": 3, "test_views": 2})
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    try:
        view.open_session(session)
        explorer = next(i for i in view.interactions if isinstance(i, RayOfPixel))
        assert not view._pixel_clicked("test_renders", 1, np.array([50.3, 40.7]))  # nothing trained yet
        session.run_until("render_held_out", LIGHT)
        carrying = session.state["held_out_cameras"]
        assert carrying.image == "test_renders" and len(carrying) == 2
        np.testing.assert_array_equal(carrying.R, session.state["test_cameras"].R)
        assert view._pixel_clicked("test_renders", 1, np.array([50.3, 40.7]))
        assert explorer.last == (1, 50, 40)
        deadline = time.monotonic() + 60
        while "ray_samples" not in session.state and time.monotonic() < deadline:
            time.sleep(0.05)
        record = [r for r in session.history if r.step == "render_view"][-1]
        assert record.params["view"] == 1 and (record.params["pixel_u"], record.params["pixel_v"]) == (50, 40)
        weights, samples = session.state["ray_weights"], session.state["ray_samples"]
        assert "pixel (50, 40)" in weights.title and len(samples) == len(weights.x) > 0
        cameras = session.state["test_cameras"]
        camera = samples.xyz @ cameras.R[1].T + cameras.t[1]
        np.testing.assert_allclose(camera[:, 2], weights.x, rtol=1e-5)  # each sample at its depth ...
        pixels = camera[:, :2] / camera[:, 2:] @ cameras.K[1][:2, :2].T + cameras.K[1][:2, 2]
        np.testing.assert_allclose(pixels, np.broadcast_to([50.0, 40.0], pixels.shape), atol=1e-3)  # ... on it
        np.testing.assert_allclose(samples.colors, weight_colors(np.asarray(weights.y).reshape(-1)))
        assert not view._pixel_clicked("images", 0, np.array([5.0, 5.0]))  # the training views: select
    finally:
        view.close()
