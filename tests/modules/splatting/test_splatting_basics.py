"""lab.modules.splatting.basics, lesson 06's teaching pipeline, against the splatting module itself: the SH
colour is the module's at degree 0, the projected covariance is the fast projection's (and the inverse of its
conic, and the readable reference's), the alphas and front-to-back compositing give the reference
rasterizer's pixels, and known answers (an isotropic Gaussian on the axis, two Gaussians in one pixel, early
termination). Tiny data: a few Gaussians before a 40 x 30 camera."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lab.core import InvalidValue, open_session
from lab.modules.splatting import BASICS, View, image_covariances, project
from lab.modules.splatting import basics as B
from lab.modules.splatting.reference import T_MIN, composite_pixel_reference, project_one_reference
from lab.modules.splatting.sh import C0

torch.set_num_threads(1)
F64 = torch.float64


def _view(s: dict) -> View:
    K = s["K"]
    return View(torch.as_tensor(s["R"], dtype=F64), torch.as_tensor(s["t"], dtype=F64), float(K[0, 0]),
                float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), s["width"], s["height"])


def _tensors(s: dict, *names: str) -> list[torch.Tensor]:
    return [torch.as_tensor(s[n], dtype=F64) for n in names]


def test_sh_dc_colour_is_c0_f_plus_half_clamped_at_zero_only():
    dc = np.array([[0.0, 1.0, -1.0], [-0.5 / C0 - 1.0, 10.0, -0.5 / C0]])
    colors = B.sh_dc_colors(dc)
    np.testing.assert_allclose(colors, [[0.5, 0.5 + C0, 0.5 - C0], [0.0, 0.5 + 10 * C0, 0.0]], atol=1e-15)
    assert colors[1, 1] > 1.0                       # not clamped at 1 (the paper's code)
    assert math.isclose(C0, 1.0 / (2.0 * math.sqrt(math.pi)), rel_tol=1e-15)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projected_covariance_is_the_fast_projections_and_the_inverse_of_its_conic(seed):
    s = B.gaussians_in_view(count=20, seed=seed).state
    cov = B.project_covariances(s["means"], s["log_scales"], s["quats"], s["R"], s["t"], s["K"])
    means, log_scales, quats = _tensors(s, "means", "log_scales", "quats")
    view = _view(s)
    _, module = image_covariances(means, log_scales, quats, view)
    np.testing.assert_allclose(cov, module.numpy(), rtol=1e-12, atol=1e-12)
    projected = project(means, log_scales, quats, view, tile_size=1024)
    assert bool(torch.all(projected.radii > 0))     # every Gaussian is drawn: inside the view
    a, b, c = projected.conics.numpy().T
    conic = np.stack([a, b, b, c], axis=1).reshape(-1, 2, 2)
    np.testing.assert_allclose(np.linalg.inv(cov), conic, rtol=1e-9)
    for i in range(3):
        one = project_one_reference(means[i], log_scales[i], quats[i], view)
        np.testing.assert_allclose(one.conic.numpy(), [conic[i, 0, 0], conic[i, 0, 1], conic[i, 1, 1]],
                                   rtol=1e-9)


def test_an_isotropic_gaussian_on_the_axis_has_covariance_f_s_over_z_squared_plus_dilation():
    f, scale, depth = 50.0, 0.2, 4.0
    K = np.array([[f, 0.0, 10.0], [0.0, f, 8.0], [0.0, 0.0, 1.0]])
    quats = np.array([[0.3, -1.2, 0.4, 2.0]])        # any rotation: the Gaussian is a ball
    cov = B.project_covariances(np.array([[0.0, 0.0, depth]]), np.full((1, 3), math.log(scale)), quats,
                                np.eye(3), np.zeros(3), K)
    np.testing.assert_allclose(cov[0], ((f * scale / depth) ** 2 + 0.3) * np.eye(2), rtol=1e-12, atol=1e-12)
    # a needle along the depth axis, off the optical axis at x = 1: only J's third column, -fx x / z^2,
    # gives it a footprint (along u)
    cov = B.project_covariances(np.array([[1.0, 0.0, depth]]), np.log([[1e-9, 1e-9, scale]]),
                                np.array([[1.0, 0.0, 0.0, 0.0]]), np.eye(3), np.zeros(3), K)
    np.testing.assert_allclose(cov[0], [[(f * scale / depth**2) ** 2 + 0.3, 0.0], [0.0, 0.3]], rtol=1e-9,
                               atol=1e-12)


@pytest.mark.parametrize("seed", [0, 3])
def test_alphas_and_compositing_give_the_reference_rasterizers_pixels(seed):
    s = B.gaussians_in_view(count=14, width=24, height=18, seed=seed).state
    colors = B.sh_dc_colors(s["sh_dc"])
    cov = B.project_covariances(s["means"], s["log_scales"], s["quats"], s["R"], s["t"], s["K"])
    px = B.pixel_alphas(s["means"], cov, s["opacities"], colors, s["R"], s["t"], s["K"], s["width"],
                        s["height"])
    image = B.composite_front_to_back(px.alphas, px.pixel_colors, s["background"])
    means, log_scales, quats = _tensors(s, "means", "log_scales", "quats")
    view = _view(s)
    tile = 1024                                     # one tile: every Gaussian in every pixel's list
    gaussians = [project_one_reference(means[i], log_scales[i], quats[i], view, tile_size=tile)
                 for i in range(len(means))]
    expected = np.array([[composite_pixel_reference(u, v, gaussians, torch.as_tensor(colors),
                                                    torch.as_tensor(s["opacities"]),
                                                    torch.as_tensor(s["background"]), tile).numpy()
                          for u in range(s["width"])] for v in range(s["height"])]).reshape(-1, 3)
    np.testing.assert_allclose(image, expected, rtol=1e-9, atol=1e-12)
    centre = (s["height"] // 2) * s["width"] + s["width"] // 2
    assert np.prod(1.0 - px.alphas[centre]) < T_MIN   # the data makes the centre end early


def test_compositing_known_answers_and_early_termination():
    colors = np.array([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]] * 3)
    alphas = np.array([[0.5, 0.5, 0.0],             # 0.5 red + 0.25 green + 0.25 background
                       [0.002, 0.5, 0.0],           # an alpha under 1/255 is skipped
                       [0.99, 0.99, 0.99]])         # T: 1e-2, 1e-4 (not under), then 1e-6: stop before
    image = B.composite_front_to_back(alphas, colors, np.array([0.2, 0.4, 0.6]))
    np.testing.assert_allclose(image[0], [0.5 + 0.05, 0.25 + 0.1, 0.15])
    np.testing.assert_allclose(image[1], [0.1, 0.5 + 0.2, 0.3])
    T = 0.01 * 0.01
    np.testing.assert_allclose(image[2], [0.99, 0.99 * 0.01, 0.0] + T * np.array([0.2, 0.4, 0.6]))


def test_the_pipeline_runs_its_steps_on_its_dataset():
    session = open_session(BASICS, "gaussians_in_view", {"count": 10, "width": 16, "height": 12}, seed=4)
    session.run_until(None)
    image = session.get("image")
    assert image.shape == (16 * 12, 3) and np.all(np.isfinite(image))
    assert session.get("alphas").shape == (16 * 12, 10)


def test_bad_input_is_named():
    s = B.gaussians_in_view(count=8, seed=1).state
    with pytest.raises(InvalidValue, match="quats"):
        B.project_covariances(s["means"], s["log_scales"], s["quats"][:, :3], s["R"], s["t"], s["K"])
    behind = s["means"].copy()
    behind[0] = s["R"].T @ (np.array([0.0, 0.0, -2.0]) - s["t"])      # camera z = -2
    with pytest.raises(InvalidValue, match="behind the camera"):
        B.project_covariances(behind, s["log_scales"], s["quats"], s["R"], s["t"], s["K"])
    with pytest.raises(InvalidValue, match="NaN"):
        B.sh_dc_colors(np.full((2, 3), np.nan))
    with pytest.raises(InvalidValue, match="pixel_colors"):
        B.composite_front_to_back(np.zeros((4, 2)), np.zeros((4, 3, 3)), np.ones(3))
