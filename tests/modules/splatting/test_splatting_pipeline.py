"""lab.modules.splatting through its PIPELINE: initialisation, a tiny
training run that lowers the loss and runs the density control, held-out evaluation by the NeRF module's
evaluation, the PLY interchange against plyfile, the density control's bookkeeping, D-SSIM, and the errors
that name the problem. Everything is tiny (3 views of 100 px, a few hundred Gaussians, tens of
iterations)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lab.core import CapacityExceeded, InvalidControl, InvalidValue, Progress, open_session
from lab.modules import splatting as S
from lab.modules.splatting import PIPELINE

torch.set_num_threads(1)

TINY = {"iterations": 60, "budget_seconds": 0.0, "sh_every": 15, "densify_from": 20, "densify_every": 20,
        "densify_until": 0.9, "opacity_reset_every": 0, "preview_every": 30}


@pytest.fixture(scope="module")
def session():
    session = open_session(PIPELINE, "synthetic_object", {"train_views": 3, "test_views": 1}, seed=1)
    session.run("initialize_gaussians", {"points": 300})
    return session


def _train(session, **controls):
    """Run train_splats's generator directly: its progress and its result."""
    state = session.state
    generator = S.train_splats(state["gaussians"], state["images"], state["cameras"], **{**TINY, **controls},
                               rng=np.random.default_rng(0))
    progress = []
    while True:
        try:
            progress.append(next(generator))
        except StopIteration as stop:
            return progress, stop.value


def random_model(n: int = 20, seed: int = 0) -> S.SplatModel:
    rng = np.random.default_rng(seed)
    return S.SplatModel(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) - 2, rng.normal(size=(n, 4)),
                        rng.normal(size=n), rng.normal(size=(n, 16, 3)), sh_degree=3)


def test_pipeline_steps_in_order():
    assert PIPELINE.name == "splatting"
    assert [s.name for s in PIPELINE.steps] == ["initialize_gaussians", "train_splats", "render_held_out",
                                                "render_view", "render_path"]
    assert PIPELINE.step("train_splats").is_generator and PIPELINE.step("render_path").is_generator
    assert [d.name for d in PIPELINE.datasets] == ["synthetic_object", "object_with_points", "nerf_synthetic",
                                                   "sfm_reconstruction"]
    written = {name for spec in PIPELINE.steps for name in spec.writes}
    assert PIPELINE.views <= written | {"images", "cameras", "test_cameras", "bounds"}
    assert {"ply", "gif"} <= set(PIPELINE.exports)
    assert set(PIPELINE.export("ply").reads) | set(PIPELINE.export("gif").reads) <= written


def test_initial_gaussians_fill_the_scene_box(session):
    model, bounds = session.state["gaussians"], session.state["bounds"]
    assert len(model) == 300 and model.sh_degree == 0
    assert np.all(np.abs(model.means - bounds.center) <= bounds.radius + 1e-6)
    np.testing.assert_allclose(torch.sigmoid(torch.as_tensor(model.opacity_logits)).numpy(), 0.1, rtol=1e-5)
    assert np.all(model.log_scales[:, 0] == model.log_scales[:, 1])          # isotropic
    assert np.all(model.sh[:, 1:] == 0)
    splats = session.state["splats"]
    assert splats.centers.shape == (300, 3) and splats.covariances.shape == (300, 3, 3)


def test_a_tiny_run_lowers_the_loss_densifies_and_raises_the_degree(session):
    progress, result = _train(session)
    assert all(isinstance(p, Progress) for p in progress) and progress[-1].iteration == 60
    previews = [p.values["preview"] for p in progress if "preview" in p.values]
    assert len(previews) == 2 and previews[0].pixels.shape == (100, 100, 3)
    losses = result.loss_curve.y[0]
    assert losses[-1] < 0.8 * losses[0]
    assert result.iterations == 60 and result.model.sh_degree == 3
    events = result.density_curve
    assert len(events.x) == 2 and events.labels == ("cloned", "split", "pruned", "held")
    assert result.clones + result.splits > 0
    assert result.gaussians_count == len(result.model) == int(events.y[3, -1])
    assert result.splats.centers.shape == (len(result.model), 3)


def test_held_out_views_are_rendered_and_evaluated_with_the_nerf_evaluation(session):
    session.run("train_splats", {**TINY, "iterations": 30})
    record = session.run("render_held_out")
    assert record.status == "ok", record.error
    assert session.state["test_renders"][0].pixels.shape == (100, 100, 3)
    assert {"psnr", "ssim"} <= set(record.metrics) and 5 < record.metrics["psnr"] < 60
    view = session.run("render_view", {"view": 0})
    assert view.status == "ok"
    np.testing.assert_array_equal(session.state["rendered"].pixels, session.state["test_renders"][0].pixels)
    with pytest.raises(InvalidControl, match="view"):
        S.render_view(session.state["model"], session.state["test_cameras"], view=5)


# --- PLY --------------------------------------------------------------------------------------------------
def test_ply_round_trip_is_exact(tmp_path):
    model = random_model()
    back = S.read_ply(S.write_ply(model, tmp_path / "splat.ply"))
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(back, name), getattr(model, name))
    assert back.sh_degree == 3
    low = S.SplatModel(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh[:, :4],
                       sh_degree=1)
    assert S.read_ply(S.write_ply(low, tmp_path / "low.ply")).sh_degree == 1


def test_ply_matches_the_original_layout_written_by_plyfile(tmp_path):
    """The paper's code writes ``PlyData([PlyElement.describe(elements, 'vertex')]).write(path)`` with every
    attribute 'f4' in its construct_list_of_attributes order: our file must be byte for byte that file."""
    import plyfile  # a test extra (pyproject.toml): the reference writer

    model = random_model(7)
    ours = S.write_ply(model, tmp_path / "ours.ply").read_bytes()
    attributes = ["x", "y", "z", "nx", "ny", "nz", *(f"f_dc_{i}" for i in range(3)),
                  *(f"f_rest_{i}" for i in range(45)), "opacity", *(f"scale_{i}" for i in range(3)),
                  *(f"rot_{i}" for i in range(4))]
    assert list(S.PROPERTIES) == attributes
    f_rest = model.sh[:, 1:].transpose(0, 2, 1).reshape(7, 45)      # features_rest.transpose(1, 2).flatten
    columns = np.concatenate([model.means, np.zeros((7, 3)), model.sh[:, 0], f_rest,
                              model.opacity_logits[:, None], model.log_scales, model.quats], axis=1)
    elements = np.empty(7, dtype=[(a, "f4") for a in attributes])
    elements[:] = list(map(tuple, columns))
    plyfile.PlyData([plyfile.PlyElement.describe(elements, "vertex")]).write(str(tmp_path / "theirs.ply"))
    assert ours == (tmp_path / "theirs.ply").read_bytes()
    read = plyfile.PlyData.read(str(tmp_path / "ours.ply"))
    assert [p.name for p in read["vertex"].properties] == attributes


def test_bad_ply_files_are_named(tmp_path):
    model = random_model(3)
    path = S.write_ply(model, tmp_path / "ok.ply")
    data = path.read_bytes()
    (tmp_path / "missing.ply").write_bytes(data.replace(b"property float opacity\n", b""))
    with pytest.raises(InvalidValue, match="lacks opacity"):
        S.read_ply(tmp_path / "missing.ply")
    (tmp_path / "short.ply").write_bytes(data[:-10])
    with pytest.raises(InvalidValue, match="ends early"):
        S.read_ply(tmp_path / "short.ply")
    (tmp_path / "text.ply").write_bytes(b"hello")
    with pytest.raises(InvalidValue, match="not a PLY"):
        S.read_ply(tmp_path / "text.ply")
    nan = S.ply_vertices(model)
    nan["scale_1"][2] = np.nan
    header = data[:data.index(b"end_header\n") + len(b"end_header\n")]
    (tmp_path / "nan.ply").write_bytes(header + nan.tobytes())
    with pytest.raises(InvalidValue, match="Gaussian 2 has a NaN"):
        S.read_ply(tmp_path / "nan.ply")


def test_model_values_are_checked_by_name(monkeypatch):
    model = random_model(4)
    with pytest.raises(InvalidValue, match=r"gaussians\.means"):
        S.SplatModel(np.full((4, 3), np.nan), model.log_scales, model.quats, model.opacity_logits, model.sh)
    with pytest.raises(InvalidValue, match=r"gaussians\.quats"):
        S.SplatModel(model.means, model.log_scales, np.zeros((4, 4)), model.opacity_logits, model.sh)
    with pytest.raises(InvalidValue, match=r"gaussians\.log_scales"):
        S.SplatModel(model.means, model.log_scales[:3], model.quats, model.opacity_logits, model.sh)
    monkeypatch.setattr("lab.modules.splatting.values.MAX_GAUSSIANS", 3)
    with pytest.raises(CapacityExceeded, match="more than the cap"):
        S.SplatModel(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh)


# --- density control and the loss -------------------------------------------------------------------------
def _trained(n: int = 6) -> S.TrainedGaussians:
    model = random_model(n, seed=3)
    t = model.tensors()
    t = {**t, "sh_dc": t["sh"][:, :1].contiguous(), "sh_rest": t["sh"][:, 1:].contiguous()}
    return S.TrainedGaussians(t, extent=1.0)


def test_density_control_clones_small_splits_large_prunes_transparent_and_moments_follow():
    gaussians = _trained()
    with torch.no_grad():
        gaussians.params["log_scales"][:] = math.log(0.005)             # small: cloned
        gaussians.params["log_scales"][1] = math.log(0.5)               # large: split
        gaussians.params["opacity_logits"][:] = 0.0
        gaussians.params["opacity_logits"][5] = -10.0                   # transparent: pruned
    loss = sum(p.sum() for p in gaussians.params.values())
    loss.backward()
    gaussians.optimizer.step()
    gaussians.grad_sum[:] = torch.tensor([1.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    gaussians.seen[:] = 1
    before = gaussians.params["means"].detach().clone()
    halved = torch.exp(gaussians.params["log_scales"][1].detach()) / 1.6
    event = gaussians.densify_and_prune(iteration=1, grad_threshold=0.5, percent_dense=0.01,
                                        min_opacity=0.005, max_screen_size=0.0,
                                        generator=torch.Generator().manual_seed(0))
    assert (event.clones, event.splits, event.prunes) == (1, 1, 1)
    assert event.count == len(gaussians) == 6 + 1 + 2 - 1 - 1
    means = gaussians.params["means"].detach()
    assert torch.equal(means[0], before[0]) and torch.equal(means[4], before[0])      # clone of Gaussian 0
    assert not any(torch.equal(m, before[1]) for m in means)                          # the split one is gone
    np.testing.assert_allclose(torch.exp(gaussians.params["log_scales"][-2:]).detach().numpy(),
                               halved.expand(2, 3).numpy(), rtol=1e-6)
    for name, p in gaussians.params.items():
        state = gaussians.optimizer.state[p]
        assert state["exp_avg"].shape == p.shape, name
        assert torch.all(state["exp_avg"][-3:] == 0), name                            # new ones start at zero
    gaussians.reset_opacity()
    assert torch.all(torch.sigmoid(gaussians.params["opacity_logits"]) <= 0.01 + 1e-6)


def test_position_learning_rate_decays_log_linearly_a_hundredfold():
    assert S.position_lr(1e-3, 0.0) == pytest.approx(1e-3)
    assert S.position_lr(1e-3, 0.5) == pytest.approx(1e-4)
    assert S.position_lr(1e-3, 1.0) == pytest.approx(1e-5)


def test_ssim_is_one_for_equal_images_and_close_to_scikit_image():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    a = rng.uniform(size=(64, 64, 3))
    b = np.clip(a + 0.1 * rng.normal(size=a.shape), 0, 1)
    assert float(S.ssim(torch.as_tensor(a), torch.as_tensor(a))) == pytest.approx(1.0)
    ours = float(S.ssim(torch.as_tensor(a), torch.as_tensor(b)))
    theirs = structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                   use_sample_covariance=False)
    assert ours == pytest.approx(theirs, abs=0.02)
    loss, l1 = S.photometric_loss(torch.as_tensor(a), torch.as_tensor(b))
    assert float(loss) == pytest.approx(0.8 * float(l1) + 0.2 * (1 - ours))


def test_training_refuses_views_that_do_not_fit_their_cameras(session):
    state = session.state
    with pytest.raises(InvalidValue, match="one camera per training view"):
        next(S.train_splats(state["gaussians"], state["images"], state["test_cameras"], **TINY,
                            rng=np.random.default_rng(0)))


def test_an_sfm_reconstruction_opens_and_its_points_start_the_gaussians(tmp_path):
    """The NeRF module's sfm_reconstruction dataset (an SfM export read back) in splatting's pipeline: its
    registered views train, its sparse points (in their colours) are where the Gaussians start."""
    from lab.core import Session
    from lab.data.exports import write_reconstruction
    from lab.data.reconstruction import SparseModel
    from lab.geometry.camera import project_points
    from lab.modules.nerf.datasets import _read_split, object_scene, write_nerf_synthetic

    reference = write_nerf_synthetic(str(tmp_path / "scene"), object_scene(0), size=32, views=(5, 1, 2))
    _, train = _read_split(reference, "train", 100, 1)
    points = np.random.default_rng(0).uniform(-0.4, 0.4, (30, 3))
    keypoints = [project_points(points, k, None, r, t)
                 for k, r, t in zip(train.K, train.R, train.t, strict=True)]
    model = SparseModel.from_tracks(
        train.K, np.tile([train.width, train.height], (len(train), 1)), train.R, train.t,
        [f"r_{i}.png" for i in range(len(train))], keypoints, points, np.full((30, 3), 200, np.uint8),
        np.zeros(30), [np.column_stack([np.arange(len(train)), np.full(len(train), p)]) for p in range(30)])
    sparse = str(write_reconstruction(str(tmp_path / "sparse"), model, "colmap"))
    loaded = PIPELINE.dataset("sfm_reconstruction").load(
        {"path": sparse, "images": str(tmp_path / "scene" / "train"), "reference": reference})
    session = Session(PIPELINE, loaded, dataset="sfm_reconstruction", seed=0)
    init = session.run("initialize_gaussians", {"source": "points", "points": 30})
    assert init.status == "ok", init.error
    gaussians = session.state["gaussians"]
    np.testing.assert_allclose(np.sort(gaussians.means, axis=0), np.sort(points, axis=0), atol=1e-5)
    np.testing.assert_allclose(S.sh_to_rgb(torch.as_tensor(gaussians.sh[:, 0])).numpy(), 200 / 255, atol=1e-5)
    assert session.run("train_splats", {"iterations": 3, "budget_seconds": 0.0}).status == "ok"
