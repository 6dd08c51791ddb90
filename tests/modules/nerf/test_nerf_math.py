"""lab.modules.nerf's math: closed forms of volume rendering and sampling, rays against projected points,
the positional encoding's known values, and every fast function against its loop reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from lab.core import InvalidValue
from lab.geometry.camera import project_points, transform_points
from lab.geometry.rotations import look_at
from lab.modules import nerf as N

torch.set_num_threads(1)


def _camera_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two cameras with different intrinsics (skew-free) looking at the origin."""
    R, t = look_at(np.array([[3.0, 0.5, 1.0], [-1.0, 2.5, 0.5]]), np.zeros((2, 3)), (0.0, 0.0, 1.0))
    K = np.array([[[120.0, 0.0, 49.5], [0.0, 110.0, 40.0], [0.0, 0.0, 1.0]],
                  [[80.0, 0.0, 30.2], [0.0, 80.0, 35.7], [0.0, 0.0, 1.0]]])
    return K, R, t


# --- rays ----------------------------------------------------------------------------------------------
def test_rays_pass_through_projected_ground_truth_points():
    """A world point X projects to pixel x; the ray through x reaches X at t = its camera depth Z."""
    K, R, t = _camera_pair()
    X = np.random.default_rng(0).uniform(-0.8, 0.8, (50, 3))
    for v in range(2):
        pixels = project_points(X, K[v], None, R[v], t[v])
        depth = transform_points(X, R[v], t[v])[:, 2]
        origins, directions = N.camera_rays(K[v:v + 1], R[v:v + 1], t[v:v + 1], pixels)
        reached = origins[0].double() + torch.as_tensor(depth)[:, None] * directions[0].double()
        np.testing.assert_allclose(reached.numpy(), X, atol=1e-5)


def test_pixel_centres_are_integers_in_the_labs_convention():
    """Pixel (j, i)'s centre is (j, i); the principal point at ((W - 1) / 2, (H - 1) / 2) is the image centre,
    so the middle pixel of an odd-sized image looks straight down the optical axis."""
    centres = N.pixel_centres(3, 2).numpy()
    np.testing.assert_array_equal(centres, [[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1]])
    K = np.array([[[50.0, 0.0, 2.0], [0.0, 50.0, 2.0], [0.0, 0.0, 1.0]]])
    _, directions = N.camera_rays(K, np.eye(3)[None], np.zeros((1, 3)), N.pixel_centres(5, 5))
    np.testing.assert_allclose(directions[0, 12].numpy(), [0.0, 0.0, 1.0], atol=1e-7)
    np.testing.assert_allclose(directions[0, 0].numpy(), [-2 / 50, -2 / 50, 1.0], atol=1e-7)


def test_rays_match_the_renderers_pixel_rays():
    from lab.data.scenes import orbit_cameras, pixel_rays

    cameras = orbit_cameras((0.0, 0.0, 0.0), num_views=3, radius=3.0, elevation=1.0, width=12, height=9)
    origins, directions = N.cameras_rays(cameras)
    for v in range(3):
        origin, expected = pixel_rays(cameras, v)
        np.testing.assert_allclose(origins[v].numpy(), np.broadcast_to(origin, (108, 3)), atol=1e-5)
        np.testing.assert_allclose(directions[v].numpy(), expected.reshape(-1, 3), atol=1e-6)


def test_camera_rays_match_the_reference():
    K, R, t = _camera_pair()
    pixels = np.random.default_rng(1).uniform(0, 100, (40, 2))
    origins, directions = N.camera_rays(K, R, t, pixels)
    ref_origins, ref_directions = N.camera_rays_reference(K, R, t, pixels)
    np.testing.assert_allclose(origins.numpy(), ref_origins, atol=1e-5)
    np.testing.assert_allclose(directions.numpy(), ref_directions, atol=1e-6)


def test_scaled_cameras_keep_pixel_centres():
    """Halving a 4 x 4 image: new pixel (0, 0) covers old pixels 0..1, so its ray is the old (0.5, 0.5)."""
    from lab.core import Cameras

    K = np.array([[60.0, 0.0, 1.5], [0.0, 60.0, 1.5], [0.0, 0.0, 1.0]])
    cameras = Cameras(K, np.eye(3), np.zeros(3), 4, 4)
    half = N.scaled_cameras(cameras, 0.5)
    assert (half.width, half.height) == (2, 2)
    _, small = N.camera_rays(half.K, half.R, half.t, np.array([[0.0, 0.0]]))
    _, big = N.camera_rays(cameras.K, cameras.R, cameras.t, np.array([[0.5, 0.5]]))
    np.testing.assert_allclose(small.numpy(), big.numpy(), atol=1e-7)


def test_nan_poses_and_distortion_are_refused():
    K, R, t = _camera_pair()
    t_bad = t.copy()
    t_bad[1, 0] = np.nan
    with pytest.raises(InvalidValue, match="camera 1 has NaN") as info:
        N.camera_rays(K, R, t_bad, np.zeros((1, 2)))
    assert info.value.field == "cameras"
    with pytest.raises(InvalidValue, match="not a rotation"):
        N.camera_rays(K, R * 2.0, t, np.zeros((1, 2)))
    from lab.core import Cameras

    with pytest.raises(InvalidValue, match="distortion"):
        N.cameras_rays(Cameras(K, R, t, 10, 10, dist=np.array([0.1, 0, 0, 0, 0])))


# --- stratified samples ------------------------------------------------------------------------------------
def test_stratified_samples_one_per_bin_and_the_reference():
    t = N.stratified_samples(2.0, 6.0, 500, 8, generator=torch.Generator().manual_seed(3))
    bins = np.floor((t.numpy() - 2.0) / 0.5)
    np.testing.assert_array_equal(bins, np.broadcast_to(np.arange(8), (500, 8)))
    u = torch.rand((500, 8), generator=torch.Generator().manual_seed(3)).numpy()
    np.testing.assert_allclose(t.numpy(), N.stratified_samples_reference(2.0, 6.0, u), atol=1e-5)
    centres = N.stratified_samples(2.0, 6.0, 1, 4, jitter=False).numpy()
    np.testing.assert_allclose(centres, [[2.5, 3.5, 4.5, 5.5]])
    # jitter spreads the samples over each whole bin
    assert t.numpy()[:, 0].min() < 2.02 and t.numpy()[:, 0].max() > 2.48


@pytest.mark.parametrize("near,far", [(2.0, 2.0), (3.0, 1.0), (-1.0, 1.0), (0.0, math.inf)])
def test_bad_near_far_is_refused(near, far):
    with pytest.raises(InvalidValue) as info:
        N.stratified_samples(near, far, 4, 8)
    assert info.value.field == "near"
    with pytest.raises(InvalidValue) as info:
        N.SceneBounds(near, far, np.zeros(3), 1.0)
    assert info.value.field == "bounds" and ("near" in info.value.reason)


# --- positional encoding -----------------------------------------------------------------------------------
def test_encoding_known_values_and_layout():
    p = torch.tensor([[0.5, 0.25, 0.0]], dtype=torch.float64)
    gamma = N.positional_encoding(p, 2).numpy()[0]
    s = math.sqrt(0.5)
    expected = [0.5, 0.25, 0.0,           # p
                1.0, s, 0.0, 0.0, s, 1.0,  # sin(pi p), cos(pi p)
                0.0, 1.0, 0.0, -1.0, 0.0, 1.0]  # sin(2 pi p), cos(2 pi p)
    np.testing.assert_allclose(gamma, expected, atol=1e-12)
    assert N.encoding_size(6) == 39 == N.positional_encoding(p, 6).shape[-1]
    assert N.encoding_size(4, include_input=False) == 24
    assert N.positional_encoding(p, 4, include_input=False).shape[-1] == 24


@pytest.mark.parametrize("frequencies,include_input", [(0, True), (3, False), (10, True)])
def test_encoding_matches_the_reference(frequencies, include_input):
    p = np.random.default_rng(2).uniform(-1, 1, (20, 3))
    fast = N.positional_encoding(torch.as_tensor(p), frequencies, include_input=include_input).numpy()
    expected = N.positional_encoding_reference(p, frequencies, include_input=include_input)
    np.testing.assert_allclose(fast, expected, atol=1e-9)


# --- volume rendering: closed forms ----------------------------------------------------------------------
def _slab(sigma: float, lo: float, hi: float, samples: int = 100):
    """One ray from t = 0 to far = 1, samples at i / samples, density ``sigma`` on [lo, hi), 0 elsewhere."""
    t = torch.arange(samples, dtype=torch.float64)[None] / samples
    density = torch.where((t >= lo - 1e-12) & (t < hi - 1e-12), sigma, 0.0)
    return t, density


@pytest.mark.parametrize("sigma,norm", [(0.5, 1.0), (3.0, 1.0), (3.0, 2.0)])
def test_homogeneous_slab_transmittance_is_exp_minus_sigma_d(sigma, norm):
    """A slab of density sigma and thickness d = 0.4 |dir| lets exp(-sigma d) through; what it absorbs
    has the slab's colour, the rest the background's."""
    t, density = _slab(sigma, 0.3, 0.7)
    rgb = torch.tensor([0.2, 0.6, 0.9], dtype=torch.float64).expand(1, 100, 3)
    out = N.volume_render(density, rgb, t, far=1.0, direction_norm=torch.tensor([norm], dtype=torch.float64),
                          background=torch.ones(3, dtype=torch.float64))
    through = math.exp(-sigma * 0.4 * norm)
    assert out.opacity.item() == pytest.approx(1.0 - through, rel=1e-9)
    np.testing.assert_allclose(out.color[0].numpy(), (1 - through) * np.array([0.2, 0.6, 0.9]) + through,
                               rtol=1e-9)
    # transmittance before the slab is 1, after it exp(-sigma d), and decays exponentially inside
    T = out.transmittance[0].numpy()
    np.testing.assert_allclose(T[:31], 1.0)
    np.testing.assert_allclose(T[70:], through, rtol=1e-9)
    np.testing.assert_allclose(T[50], math.exp(-sigma * 0.2 * norm), rtol=1e-9)


def test_a_single_opaque_step_ends_the_ray_there():
    t, density = _slab(1e4, 0.42, 1.0)
    rgb = torch.zeros((1, 100, 3), dtype=torch.float64)
    rgb[0, 42] = torch.tensor([1.0, 0.0, 0.0])
    out = N.volume_render(density, rgb, t, far=1.0, background=torch.ones(3, dtype=torch.float64))
    assert out.depth.item() == pytest.approx(0.42, abs=1e-9)
    assert out.opacity.item() == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(out.color[0].numpy(), [1.0, 0.0, 0.0], atol=1e-9)
    weights = out.weights[0].numpy()
    assert weights[42] == pytest.approx(1.0, abs=1e-9) and weights.sum() == pytest.approx(1.0)


def test_empty_space_shows_the_background_at_far():
    t = torch.linspace(2.0, 5.9, 16, dtype=torch.float64)[None]
    out = N.volume_render(torch.zeros_like(t), torch.rand((1, 16, 3), dtype=torch.float64), t, far=6.0,
                          background=torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64))
    assert out.opacity.item() == 0.0 and out.depth.item() == 6.0
    np.testing.assert_array_equal(out.color[0].numpy(), [1.0, 1.0, 1.0])


def test_volume_render_matches_the_reference_and_has_finite_gradients():
    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(2.0, 6.0, (30, 24)), axis=1)
    sigma = rng.exponential(2.0, (30, 24))
    rgb = rng.uniform(0, 1, (30, 24, 3))
    norm = rng.uniform(0.9, 1.4, 30)
    background = np.array([1.0, 0.5, 0.0])
    sigma_t = torch.tensor(sigma, requires_grad=True)
    fast = N.volume_render(sigma_t, torch.as_tensor(rgb), torch.as_tensor(t), far=6.0,
                           direction_norm=torch.as_tensor(norm), background=torch.as_tensor(background))
    ref = N.volume_render_reference(sigma, rgb, t, 6.0, norm, background)
    for name, expected in ref.items():
        np.testing.assert_allclose(getattr(fast, name).detach().numpy(), expected, rtol=1e-9, atol=1e-12,
                                   err_msg=name)
    fast.color.sum().backward()
    assert sigma_t.grad is not None and torch.all(torch.isfinite(sigma_t.grad))


def test_volume_render_refuses_unsorted_samples_and_bad_shapes():
    t = torch.tensor([[1.0, 3.0, 2.0]])
    with pytest.raises(InvalidValue, match="sorted"):
        N.volume_render(torch.ones(1, 3), torch.ones(1, 3, 3), t, far=4.0)
    with pytest.raises(InvalidValue, match="expected sigma"):
        N.volume_render(torch.ones(1, 2), torch.ones(1, 3, 3), torch.ones(1, 3), far=4.0)


# --- inverse-CDF sampling ----------------------------------------------------------------------------------
def _piecewise_cdf(x: np.ndarray, edges: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """CDF of the density that puts ``mass`` uniformly in each bin of ``edges``."""
    cdf = np.concatenate([[0.0], np.cumsum(mass)])
    return np.interp(x, edges, cdf)


def test_inverse_cdf_samples_follow_the_piecewise_constant_pdf():
    """Kolmogorov-Smirnov against the exact CDF (fixed seed); a wrong CDF (uniform) is rejected."""
    edges = np.array([0.0, 1.0, 2.0, 4.0])
    weights = np.array([1.0, 2.0, 1.0])
    samples = N.sample_pdf(torch.as_tensor(edges)[None], torch.as_tensor(weights)[None], 20000,
                           generator=torch.Generator().manual_seed(0))[0].numpy()
    mass = weights / weights.sum()  # the PDF's epsilon (1e-5 per bin) is far below what KS can see here
    good = stats.kstest(samples, lambda x: _piecewise_cdf(x, edges, mass))
    assert good.pvalue > 0.01 and good.statistic < 0.012
    wrong = stats.kstest(samples, stats.uniform(0, 4).cdf)
    assert wrong.pvalue < 1e-6
    assert samples.min() >= 0.0 and samples.max() < 4.0


def test_inverse_cdf_deterministic_quantiles_known_answer():
    """u = (k + 0.5) / 4 = 1/8, 3/8, 5/8, 7/8 of the CDF (0, 1/4, 3/4, 1) over edges 0, 1, 2, 4: 7/8 is half
    way through the last bin's quarter, so half way from 2 to 4."""
    edges = torch.tensor([[0.0, 1.0, 2.0, 4.0]], dtype=torch.float64)
    got = N.sample_pdf(edges, torch.tensor([[1.0, 2.0, 1.0]], dtype=torch.float64) * 1e6, 4,
                       deterministic=True)[0].numpy()
    np.testing.assert_allclose(got, [0.5, 1.25, 1.75, 3.0], atol=1e-6)


def test_sample_pdf_matches_the_reference():
    rng = np.random.default_rng(5)
    edges = np.sort(rng.uniform(0, 10, (25, 9)), axis=1)
    weights = rng.uniform(0, 1, (25, 8)) * (rng.uniform(0, 1, (25, 8)) > 0.4)
    weights[3] = 0.0  # no mass at all: uniform over the bins' PDF of epsilons
    fast = N.sample_pdf(torch.as_tensor(edges), torch.as_tensor(weights), 16,
                        generator=torch.Generator().manual_seed(9)).numpy()
    u = torch.rand((25, 16), generator=torch.Generator().manual_seed(9), dtype=torch.float64).numpy()
    np.testing.assert_allclose(fast, N.sample_pdf_reference(edges, weights, u), atol=1e-9)


def test_hierarchical_samples_gather_where_the_weight_is():
    """An opaque step at sample 9 of 20 (t = 0.45): its interval [0.45, 0.5] holds all the weight, so the
    fine samples fall there (but for the PDF's epsilon)."""
    t, density = _slab(1e4, 0.45, 1.0, samples=20)
    out = N.volume_render(density, torch.rand((1, 20, 3), dtype=torch.float64), t, far=1.0)
    merged = N.hierarchical_samples(t, out.weights, 1.0, 64, generator=torch.Generator().manual_seed(1))
    assert merged.shape == (1, 84) and torch.all(torch.diff(merged, dim=-1) >= 0)
    fine = merged[0].numpy()
    assert np.sum((fine >= 0.45) & (fine <= 0.5)) == 64 + 2  # the fine ones and the coarse 0.45 and 0.5
