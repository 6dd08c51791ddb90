"""lab.modules.splatting as a registered module: the start from a dataset's points, the Gaussians of a
clicked pixel (their weights rebuild the rendered pixel), the orbit, the exports through ``vision-lab
export``, and bad input refused by name (a camera looking away is an empty image, not an error). Tiny:
3 views of 100 px, a few hundred Gaussians, tens of iterations."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lab.core import CapacityExceeded, Cameras, InvalidControl, InvalidValue, PointCloud, open_session
from lab.modules import MODULES, get_pipeline
from lab.modules import splatting as S

torch.set_num_threads(1)

TINY = {"iterations": 30, "budget_seconds": 0.0, "sh_every": 10, "densify_from": 10, "densify_every": 10,
        "densify_until": 0.9, "opacity_reset_every": 0, "preview_every": 30}


@pytest.fixture(scope="module")
def trained():
    session = open_session(get_pipeline("splatting"), "object_with_points",
                           {"train_views": 3, "test_views": 2, "points": 600}, seed=1)
    for step, controls in (("initialize_gaussians", {"points": 300}), ("train_splats", TINY),
                           ("render_held_out", {})):
        record = session.run(step, controls)
        assert record.status == "ok", record.error
    return session


def test_splatting_is_registered():
    assert "splatting" in MODULES
    assert get_pipeline("splatting") is S.PIPELINE


def test_the_dataset_points_lie_on_the_object_and_start_the_gaussians(trained):
    cloud = trained.state["sfm_points"]
    assert isinstance(cloud, PointCloud) and len(cloud) == 600
    # every point is seen by some training view at a pixel centre, at that pixel's exact depth
    cameras, images, depths = trained.state["cameras"], trained.state["images"], trained.truth["train_depths"]
    error = np.full(len(cloud), np.inf)
    for view in range(len(cameras)):
        camera = cloud.xyz @ cameras.R[view].T + cameras.t[view]
        pixels = camera[:, :2] / camera[:, 2:] @ cameras.K[view][:2, :2].T + cameras.K[view][:2, 2]
        u, v = np.round(pixels).astype(int).T
        inside = (abs(pixels - np.round(pixels)).max(axis=1) < 1e-6) & (u >= 0) & (u < 100) & (v >= 0) \
            & (v < 100)
        here = np.where(inside, depths[view, v.clip(0, 99), u.clip(0, 99)], np.inf)
        error = np.minimum(error, abs(here - camera[:, 2]))
    assert error.max() < 1e-9
    bounds = trained.state["bounds"]
    assert np.all(np.linalg.norm(cloud.xyz - bounds.center, axis=1) <= bounds.radius)
    model = trained.state["gaussians"]
    assert len(model) == 300
    on_cloud = (model.means[:, None, :] == cloud.xyz[None].astype(np.float32)).all(axis=2).any(axis=1)
    assert on_cloud.all()
    assert not np.allclose(images[0].pixels, 1.0)


def test_source_points_needs_points_and_random_ignores_them(trained):
    state, rng = trained.state, np.random.default_rng(0)
    with pytest.raises(InvalidControl, match="brings no points"):
        S.initialize_gaussians(state["bounds"], None, source="points", points=50, rng=rng)
    random = S.initialize_gaussians(state["bounds"], state["sfm_points"], source="random", points=50, rng=rng)
    cloud = state["sfm_points"].xyz.astype(np.float32)
    assert not (random.gaussians.means[:, None] == cloud[None]).all(axis=2).any()
    with pytest.raises(InvalidValue, match="sfm_points"):
        S.initialize_gaussians(state["bounds"], state["images"], points=50, rng=rng)
    few = S.initialize_gaussians(state["bounds"], PointCloud(state["sfm_points"].xyz[:20]), points=50,
                                 fill_random=False, rng=rng)
    assert len(few.gaussians) == 20
    np.testing.assert_allclose(S.sh_to_rgb(torch.as_tensor(few.gaussians.sh[:, 0])).numpy(), 0.5, atol=1e-6)


def test_too_few_points_are_filled_with_random_points_of_the_scene_box(trained):
    """20 points of the cloud and 30 drawn in the box (the default): the cloud's first, in grey, then
    random ones, inside the cube of half-side radius about the centre and off the cloud."""
    state, rng = trained.state, np.random.default_rng(0)
    bounds, cloud = state["bounds"], PointCloud(state["sfm_points"].xyz[:20])
    filled = S.initialize_gaussians(bounds, cloud, points=50, rng=rng).gaussians
    assert len(filled) == 50
    np.testing.assert_array_equal(filled.means[:20], cloud.xyz.astype(np.float32))
    extra = filled.means[20:]
    assert np.all(np.abs(extra - bounds.center) <= bounds.radius * (1 + 1e-6))
    assert not (extra[:, None] == cloud.xyz[None].astype(np.float32)).all(axis=2).any()
    assert np.ptp(S.sh_to_rgb(torch.as_tensor(filled.sh[20:, 0])).numpy()) > 0.5     # random colours
    enough = S.initialize_gaussians(bounds, cloud, points=20, rng=rng).gaussians
    np.testing.assert_array_equal(enough.means, cloud.xyz.astype(np.float32))


def test_a_pixels_gaussians_rebuild_the_rendered_pixel(trained):
    model, cameras = trained.state["model"], trained.state["test_cameras"]
    image = S.render_model(model, cameras, 1)
    covered = 0
    for u, v in ((50, 50), (40, 61), (0, 0), (99, 99), (17, 80)):
        found = S.pixel_contributions(model, cameras, 1, u, v)
        np.testing.assert_allclose(np.clip(found.color, 0, 1), image[v, u], atol=2e-5)
        assert np.all(np.diff(found.depths) >= 0)                       # front to back
        np.testing.assert_allclose(found.weights, found.alphas * found.before)
        np.testing.assert_allclose(found.before[1:], found.before[:-1] * (1 - found.alphas[:-1]), rtol=1e-6)
        left = found.before[-1] * (1 - found.alphas[-1]) if len(found) else 1.0
        assert found.remaining == pytest.approx(left)
        covered += len(found) > 0
    assert covered >= 2


def test_render_view_lists_the_pixel_and_draws_its_gaussians(trained):
    record = trained.run("render_view", {"view": 1, "pixel_u": 50, "pixel_v": 50})
    assert record.status == "ok", record.error
    found = S.pixel_contributions(trained.state["model"], trained.state["test_cameras"], 1, 50, 50)
    chart, splats = trained.state["pixel_gaussians"], trained.state["pixel_splats"]
    shown = min(len(found), S.PIXEL_LIST)
    assert chart.kind == "bar" and chart.categories == tuple(f"#{i}" for i in found.ids[:shown])
    np.testing.assert_allclose(chart.y[2], found.weights[:shown])
    np.testing.assert_allclose(splats.xyz, trained.state["model"].means[found.ids])
    assert record.metrics["pixel_count"] == len(found)
    with pytest.raises(InvalidControl, match="pixel_v"):
        S.render_view(trained.state["model"], trained.state["test_cameras"], view=0, pixel_u=3, pixel_v=100)
    carrying = trained.state["held_out_cameras"]
    assert carrying.image == "test_renders" and len(carrying) == 2


def test_a_camera_looking_away_renders_the_background_and_lists_no_gaussian(trained):
    model, cameras = trained.state["model"], trained.state["test_cameras"]
    flip = np.diag([-1.0, 1.0, -1.0])                 # turned half a turn about its y axis, same centre
    R = flip @ cameras.R[0]
    away = Cameras(cameras.K[:1], R[None], (-R @ cameras.centers[0])[None], cameras.width, cameras.height)
    result = S.render_view(model, away, view=0, pixel_u=50, pixel_v=50)
    np.testing.assert_array_equal(result.rendered.pixels, np.ones((100, 100, 3), np.float32))
    assert result.pixel_count == 0 and result.pixel_transmittance == 1.0 and len(result.pixel_splats) == 0
    assert result.pixel_gaussians.categories == ("none",)


def test_the_orbit_is_rendered_at_the_training_height(trained):
    record = trained.run("render_path", {"frames": 3, "scale": 0.5})
    assert record.status == "ok", record.error
    frames, path = trained.state["path_frames"], trained.state["path_cameras"]
    assert len(frames.images) == 3 and frames.images[0].pixels.shape == (50, 50, 3)
    assert path.image == "path_frames"
    centre = trained.state["bounds"].center
    training = np.linalg.norm(trained.state["cameras"].centers - centre, axis=1).mean()
    np.testing.assert_allclose(np.linalg.norm(path.centers - centre, axis=1), training, rtol=0.05)


def test_exports_write_a_ply_that_reimports_and_a_gif(trained, tmp_path):
    import imageio.v3 as iio

    written = S.PIPELINE.export("ply").write(trained.state, trained.metrics, tmp_path / "sub" / "splat.ply")
    back, model = S.read_ply(written), trained.state["model"]
    np.testing.assert_array_equal(back.means, model.means)
    np.testing.assert_array_equal(back.sh, model.sh)
    trained.run("render_path", {"frames": 2, "scale": 0.5})
    gif = S.PIPELINE.export("gif").write(trained.state, trained.metrics, tmp_path / "orbit.gif")
    assert iio.imread(gif, index=None).shape[:3] == (2, 50, 50)


def test_vision_lab_export_splatting_ply_trains_and_writes_the_splats(tmp_path):
    from typer.testing import CliRunner

    from lab import cli

    out = tmp_path / "splats.ply"
    args = ["export", "splatting", "--format", "ply", "--out", str(out), "--option", "train_views=3",
            "--option", "test_views=1", "--set", "initialize_gaussians.points=200",
            "--set", "train_splats.iterations=10", "--set", "train_splats.budget_seconds=0"]
    result = CliRunner().invoke(cli.app, args, prog_name="vision-lab")
    assert result.exit_code == 0, result.output
    assert "3D Gaussian splatting PLY" in result.stdout
    model = S.read_ply(out)
    assert 100 < len(model) < 1000 and model.sh_degree == 0


def test_exports_before_training_and_ply_over_the_cap_are_named(tmp_path, monkeypatch):
    from lab.core import MissingInput

    with pytest.raises(MissingInput, match="train_splats"):
        S.PIPELINE.export("ply").write({}, {}, tmp_path / "none.ply")
    rng = np.random.default_rng(0)
    model = S.SplatModel(rng.normal(size=(5, 3)), np.full((5, 3), -2.0), np.tile([1.0, 0, 0, 0], (5, 1)),
                         np.zeros(5), np.zeros((5, 16, 3)))
    path = S.write_ply(model, tmp_path / "five.ply")
    monkeypatch.setattr("lab.modules.splatting.values.MAX_GAUSSIANS", 4)
    with pytest.raises(CapacityExceeded, match="5 Gaussians is more than the cap of 4"):
        S.read_ply(path)


def test_cancelling_training_keeps_the_gaussians_trained_so_far(trained):
    from lab.core import Cancelled

    state = trained.state
    generator = S.train_splats(state["gaussians"], state["images"], state["cameras"],
                               **{**TINY, "iterations": 1000}, rng=np.random.default_rng(0))
    assert [next(generator).iteration for _ in range(2)] == [10, 20]
    with pytest.raises(StopIteration) as stop:  # what the runner does on Cancel: Cancelled thrown in
        generator.throw(Cancelled("train_splats", "cancelled by the user"))
    result = stop.value.value
    assert result.iterations == 20 and "stopped after 20 of 1000 iterations" in result.warnings[0]
    renders = S.render_held_out(result.model, state["test_cameras"]).test_renders
    assert renders[0].pixels.shape == (100, 100, 3)


def test_a_run_to_its_iterations_has_no_warning(trained):
    state = trained.state
    generator = S.train_splats(state["gaussians"], state["images"], state["cameras"],
                               **{**TINY, "iterations": 10}, rng=np.random.default_rng(0))
    while True:
        try:
            next(generator)
        except StopIteration as stop:
            assert stop.value.iterations == 10 and stop.value.warnings == ()
            break
