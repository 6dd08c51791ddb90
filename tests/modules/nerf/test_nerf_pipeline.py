"""lab.modules.nerf's steps through its PIPELINE (registered in lab.modules.MODULES): shapes, a tiny training
run that lowers the loss, held-out evaluation, and the errors that name the problem. Networks here are tiny
(16 samples, a 32-wide MLP, a few dozen iterations) and torch runs on one thread."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from modules.texture_helpers import drive

from lab.core import Image, ImageSet, InvalidControl, InvalidValue, Progress, open_session
from lab.modules import MODULES, get_pipeline
from lab.modules import nerf as N
from lab.modules.nerf import PIPELINE

torch.set_num_threads(1)

TINY = {"samples": 16, "hidden": 32, "layers": 2, "batch_rays": 256, "iterations": 40, "preview_every": 20}


@pytest.fixture(scope="module")
def session():
    session = open_session(PIPELINE, "synthetic_object", {"train_views": 3, "test_views": 1}, seed=2)
    session.run("generate_rays")
    session.run("encode_positions")
    return session


def _train(session, **controls):
    """Run train_nerf's generator directly: its progress and its result."""
    state = session.state
    return drive(N.train_nerf(state["rays"], state["encoding"], state["cameras"], **{**TINY, **controls},
                              rng=np.random.default_rng(0)))


def test_pipeline_steps_in_order_and_registered():
    assert "nerf" in MODULES and get_pipeline("nerf") is PIPELINE
    assert PIPELINE.name == "nerf" and PIPELINE.title == "Neural radiance fields"
    assert [s.name for s in PIPELINE.steps] == ["generate_rays", "encode_positions", "fit_image_2d",
                                                "train_nerf", "render_held_out", "render_view", "render_path",
                                                "extract_mesh"]
    assert all(PIPELINE.step(name).is_generator for name in ("fit_image_2d", "train_nerf", "render_path"))
    assert [d.name for d in PIPELINE.datasets] == ["synthetic_object", "nerf_synthetic", "sfm_reconstruction"]
    assert PIPELINE.dataset("nerf_synthetic").takes_path and PIPELINE.dataset("sfm_reconstruction").takes_path
    written = {name for spec in PIPELINE.steps for name in spec.writes}
    dataset = {"images", "cameras", "test_cameras", "bounds"}
    assert PIPELINE.views <= written | dataset
    assert sorted(PIPELINE.exports) == ["gif", "glb", "ply"]
    assert PIPELINE.export("ply").reads == ("mesh",) and PIPELINE.export("gif").reads == ("path_frames",)


def test_rays_carry_their_pixels_colours(session):
    rays, images = session.state["rays"], session.state["images"]
    assert len(rays) == 3 * 100 * 100 and rays.origins.dtype == np.float32
    np.testing.assert_array_equal(rays.colors[10000:20000].reshape(100, 100, 3), images[1].pixels)
    np.testing.assert_array_equal(rays.views[::10000], [0, 1, 2])
    lines = session.state["ray_lines"]
    assert len(lines) == 200
    lengths = np.linalg.norm(lines.end - lines.start, axis=1)
    assert np.all(lengths > 0)


def test_generate_rays_refuses_views_that_do_not_fit_their_cameras(session):
    state = session.state
    images = state["images"].images
    smaller = ImageSet((images[0], Image(images[1].pixels[:50, :50]), images[2]))
    with pytest.raises(InvalidValue, match="view 1 is 50x50") as info:
        N.generate_rays(smaller, state["cameras"], state["bounds"])
    assert info.value.field == "images"
    with pytest.raises(InvalidValue, match="2 images for 3 cameras"):
        N.generate_rays(ImageSet(images[:2]), state["cameras"], state["bounds"])
    with pytest.raises(InvalidValue, match="SceneBounds"):
        N.generate_rays(state["images"], state["cameras"], (2.0, 6.0))


def test_encoding_step_writes_the_configuration_and_its_plot(session):
    result = N.encode_positions(frequencies=3, direction_frequencies=2)
    assert result.encoding == N.EncodingConfig(3, 2, True)
    assert result.position_features == 21 and result.direction_features == 15
    assert result.encoding_plot.y.shape == (4, 401)  # p and sin(2^k pi p), k < 3
    x = result.encoding_plot.x
    np.testing.assert_allclose(result.encoding_plot.y[3], np.sin(4 * np.pi * x), atol=1e-12)


def test_a_tiny_training_run_lowers_the_loss_and_shows_previews(session):
    progress, result = _train(session)
    assert all(isinstance(p, Progress) for p in progress)
    assert [p.iteration for p in progress] == [10, 20, 30, 40]
    curve = result.loss_curve.y[0]  # running means over 2 iterations: the first is the untrained network's
    assert curve[-1] < 0.75 * curve[0] and progress[-1].loss < progress[0].loss
    assert "PSNR" in progress[-1].message and progress[0].total == 40
    previews = [p.values["preview"] for p in progress if "preview" in p.values]
    assert len(previews) == 2 and previews[0].pixels.shape == (64, 64, 3)
    assert result.iterations == 40 and result.train_psnr > 0
    assert result.loss_curve.y.shape[1] == result.psnr_curve.y.shape[1]
    assert isinstance(result.model, N.NerfCheckpoint) and result.model.config.samples == 16


def test_training_is_reproducible_from_its_rng(session):
    _, a = _train(session, iterations=3)
    _, b = _train(session, iterations=3)
    for key, value in a.model.weights.items():
        np.testing.assert_array_equal(value, b.model.weights[key])


def test_hierarchical_training_and_a_time_budget(session):
    _, fine = _train(session, iterations=4, fine_samples=8)
    assert fine.model.config.fine_samples == 8 and fine.iterations == 4 and fine.warnings == ()
    _, timed = _train(session, iterations=100000, budget_seconds=0.3)  # the budget ends the run, no warning
    assert 1 < timed.iterations < 100000 and timed.warnings == ()


def test_held_out_evaluation_and_a_rendered_view(session):
    session.run("train_nerf", TINY)
    record = session.run("render_held_out")
    assert record.status == "ok"
    assert {"psnr", "ssim", "depth_mae", "render_seconds"} <= set(record.metrics)
    assert 5 < record.metrics["psnr"] < 60 and -1 <= record.metrics["ssim"] <= 1
    assert session.state["test_depth"].shape == (1, 100, 100)
    bounds = session.state["bounds"]
    assert np.all(session.state["test_depth"] >= bounds.near - 1e-4)
    assert np.all(session.state["test_depth"] <= bounds.far + 1e-4)
    session.run("render_view", {"pixel_u": 50, "pixel_v": 40})
    state = session.state
    assert state["rendered"].pixels.shape == (100, 100, 3) and state["depth_map"].pixels.shape == (100, 100)
    weights = state["ray_weights"]
    assert weights.x.shape == (16,) and np.all(np.diff(weights.x) > 0) and weights.y.sum() <= 1 + 1e-5


def test_render_view_errors_name_the_control(session):
    if "model" not in session.state:
        session.run("train_nerf", {**TINY, "iterations": 2})
    model, cameras = session.state["model"], session.state["test_cameras"]
    with pytest.raises(InvalidControl) as info:
        N.render_view(model, cameras, view=5)
    assert info.value.field == "view"
    with pytest.raises(InvalidControl) as info:
        N.render_view(model, cameras, pixel_u=100)
    assert info.value.field == "pixel_u"
    with pytest.raises(InvalidValue) as info:
        N.render_held_out("not a model", cameras)
    assert info.value.field == "model"


def test_evaluation_known_answers():
    a = np.zeros((8, 8, 3))
    assert N.image_psnr(a, a + 0.1) == pytest.approx(20.0)
    assert N.image_psnr(a, a) == float("inf")
    rng = np.random.default_rng(0)
    b = rng.uniform(0, 1, (16, 16, 3))
    assert N.image_ssim(b, b) == pytest.approx(1.0)
    assert N.image_ssim(b, rng.uniform(0, 1, (16, 16, 3))) < 0.2
    truth = np.array([[2.0, np.inf], [3.0, np.inf]])
    assert N.depth_error(np.array([[2.5, 9.0], [2.0, 9.0]]), truth) == pytest.approx(0.75)
    assert N.evaluate_held_out({}, {}) == {}


def test_a_batch_too_large_for_memory_is_refused_before_training(session):
    from lab.core import CapacityExceeded

    with pytest.raises(CapacityExceeded) as info:
        _train(session, batch_rays=65536, samples=64)
    assert info.value.field == "batch_rays"
    with pytest.raises(CapacityExceeded) as info:
        _train(session, batch_rays=8192, samples=64, hidden=512)
    assert info.value.field == "hidden"
