"""The fast Gaussian rasterizer against its readable reference (images and every parameter's gradient), a
single Gaussian against its closed form, early termination, empty views, and the math underneath
(quaternions, covariances, spherical harmonics, projection, tile binning). Scenes are tiny: the reference
composites one pixel at a time."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lab.core import CapacityExceeded
from lab.modules.splatting import gaussians as G
from lab.modules.splatting import rasterize as RZ
from lab.modules.splatting import reference as REF
from lab.modules.splatting.sh import C0, sh_basis, sh_colors

torch.set_num_threads(1)
F64 = torch.float64
NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh")


def camera(width: int = 36, height: int = 26, *, R: torch.Tensor | None = None) -> G.View:
    """A pinhole at the origin looking down +z (or rotated by ``R``), off-centre principal point."""
    return G.View(torch.eye(3, dtype=F64) if R is None else R, torch.zeros(3, dtype=F64), 28.0, 30.0,
                  0.47 * width, 0.52 * height, width, height)


def random_scene(seed: int, count: int = 24) -> dict[str, torch.Tensor]:
    """Gaussians in front of ``camera()`` with every awkward case the rasterizer meets: overlapping ones,
    tiny and huge ones, one behind the camera and one nearer than the near plane, ones straddling and
    outside the image edges, opaque ones (alpha clamped at 0.99) and a stack deep enough to end pixels
    early (T < 1e-4)."""
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(count, 2, generator=g, dtype=F64) - 0.5) * torch.tensor([1.6, 1.2], dtype=F64)
    z = 1.5 + 2.0 * torch.rand(count, 1, generator=g, dtype=F64)
    means = torch.cat([xy * z, z], dim=1)
    log_scales = torch.log(0.03 + 0.25 * torch.rand(count, 3, generator=g, dtype=F64))
    quats = torch.randn(count, 4, generator=g, dtype=F64)
    logits = 2.0 * torch.randn(count, generator=g, dtype=F64)
    sh = 0.4 * torch.randn(count, 16, 3, generator=g, dtype=F64)
    means[0] = torch.tensor([0.1, 0.0, -1.0])             # behind the camera
    means[1] = torch.tensor([0.0, 0.05, 0.1])             # in front, but nearer than the near plane
    log_scales[2] = torch.log(torch.tensor([1.5, 1.0, 0.8]))   # huge: covers the image
    log_scales[3] = -7.0                                   # tiny: the 0.3 px dilation is all it has
    means[4] = torch.tensor([-0.94 * 2.0, 0.1, 2.0])       # straddling the left edge
    means[5] = torch.tensor([0.3, 0.98 * 2.5, 2.5])        # straddling the bottom edge
    means[6] = torch.tensor([3.5, 0.0, 2.0])               # outside, its footprint reaching in
    for k in range(7, 11):                                 # an opaque stack over one spot
        means[k] = torch.tensor([0.05 * k - 0.4, -0.1, 1.2 + 0.1 * k])
        logits[k] = 6.0
    return {"means": means, "log_scales": log_scales, "quats": quats, "opacity_logits": logits, "sh": sh}


def both(scene: dict[str, torch.Tensor], view: G.View, background: torch.Tensor, degree: int = 3,
         tile_size: int = 16):
    """Images and gradients (of a fixed random linear loss) of the fast path and the reference."""
    out = []
    for draw in (RZ.render, REF.render_reference):
        params = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
        image = draw(*(params[k] for k in NAMES), view, sh_degree=degree, background=background,
                     tile_size=tile_size)
        image = image.image if isinstance(image, RZ.Rendering) else image
        weights = torch.randn(image.shape, generator=torch.Generator().manual_seed(5), dtype=F64)
        if image.requires_grad:           # the reference's image of nothing drawn is a constant
            (image * weights).sum().backward()
        grads = {k: torch.zeros_like(p) if p.grad is None else p.grad for k, p in params.items()}
        out.append((image.detach(), grads))
    return out


def assert_close_gradients(fast: dict, slow: dict) -> None:
    for name in NAMES:
        a, b = fast[name], slow[name]
        assert a is not None and b is not None, name
        bound = 1e-4 * torch.clamp(b.abs(), min=1.0)
        assert torch.all((a - b).abs() <= bound), f"{name}: {(a - b).abs().max():.3g}"


@pytest.mark.parametrize(("seed", "degree", "tile_size"), [(0, 3, 16), (1, 1, 8), (2, 0, 16)])
def test_fast_rasterizer_matches_the_reference_in_image_and_every_gradient(seed, degree, tile_size):
    view = camera()
    background = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    (fast_image, fast_grads), (slow_image, slow_grads) = both(random_scene(seed), view, background, degree,
                                                              tile_size)
    assert fast_image.shape == (26, 36, 3)
    assert (fast_image - slow_image).abs().max() <= 1e-5
    assert (fast_image - background).abs().max() > 0.1        # something was drawn
    assert_close_gradients(fast_grads, slow_grads)
    for name in NAMES:                                         # and the gradients are not trivially zero
        assert fast_grads[name].abs().max() > 1e-3, name
    assert torch.all(fast_grads["means"][0] == 0) and torch.all(fast_grads["means"][1] == 0)  # culled


def test_a_camera_looking_away_renders_the_background_and_zero_gradients():
    turned = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=F64))     # looking down -z
    background = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    scene = {k: v[1:] for k, v in random_scene(3).items()}    # all in front of camera(): behind this one
    (image, grads), (slow, _) = both(scene, camera(R=turned), background)
    expected = background.expand(26, 36, 3)
    assert torch.equal(image, expected) and torch.equal(slow, expected)
    assert all(torch.all(grads[name] == 0) for name in NAMES)
    empty = {k: v[:0] for k, v in random_scene(3).items()}
    assert torch.equal(RZ.render(*(empty[k] for k in NAMES), camera(), sh_degree=0,
                                 background=background).image, expected)


def test_a_single_isotropic_gaussian_has_its_closed_form_footprint():
    """On the optical axis at depth d, scale s: Sigma' = ((f s / d)^2 + 0.3) I, so a pixel at distance r from
    the principal point has alpha = o exp(-r^2 / (2 sigma'^2)) (0 below 1/255), colour C0 dc + 0.5."""
    f, d, s, o = 30.0, 2.0, 0.1, 0.8
    view = G.View(torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64), f, f, 15.0, 14.0, 32, 32)
    sh = torch.zeros(1, 16, 3, dtype=F64)
    sh[0, 0] = torch.tensor([0.7, -0.3, 0.2])
    background = torch.tensor([1.0, 1.0, 1.0], dtype=F64)
    rendering = RZ.render(torch.tensor([[0.0, 0.0, d]], dtype=F64),
                          torch.full((1, 3), math.log(s), dtype=F64),
                          torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),
                          torch.tensor([math.log(o / (1 - o))], dtype=F64), sh, view, sh_degree=0,
                          background=background)
    variance = (f * s / d) ** 2 + 0.3
    v, u = np.mgrid[0:32, 0:32]
    alpha = o * np.exp(-((u - 15.0) ** 2 + (v - 14.0) ** 2) / (2 * variance))
    alpha[alpha < 1 / 255] = 0
    colour = C0 * sh[0, 0].numpy() + 0.5
    expected = alpha[..., None] * colour + (1 - alpha[..., None]) * 1.0
    np.testing.assert_allclose(rendering.image.numpy(), expected, atol=1e-12)
    assert int(rendering.radii[0]) == math.ceil(3 * math.sqrt(variance + math.sqrt(0.1)))


def test_compositing_stops_before_the_gaussian_that_would_take_transmittance_below_1e_4():
    """Three opaque Gaussians (alpha 0.99) over one pixel: after two T = 1e-4 (kept, not below), the third
    would make it 1e-6, so the pixel ends there and the third's colour never shows."""
    view = G.View(torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64), 30.0, 30.0, 8.0, 8.0, 17, 17)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.5], [0.0, 0.0, 3.0]], dtype=F64)
    sh = torch.zeros(3, 16, 3, dtype=F64)
    sh[:, 0] = (torch.eye(3, dtype=F64) - 0.5) / C0        # red, green, blue
    params = (means, torch.full((3, 3), -1.0, dtype=F64), torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=F64),
              torch.full((3,), 10.0, dtype=F64), sh)
    background = torch.tensor([0.5, 0.5, 0.5], dtype=F64)
    image = RZ.render(*params, view, sh_degree=0, background=background).image
    slow = REF.render_reference(*params, view, sh_degree=0, background=background)
    T1 = 1 - 0.99
    T2 = T1 * (1 - 0.99)
    assert T2 >= 1e-4 > T2 * (1 - 0.99)
    np.testing.assert_allclose(image[8, 8].numpy(), np.array([0.99, 0.99 * T1, 0.0]) + T2 * 0.5, atol=1e-12)
    assert torch.allclose(image, slow, atol=1e-12)


def test_float32_training_path_agrees_with_the_float64_reference():
    scene = random_scene(4)
    view = camera()
    background = torch.tensor([1.0, 1.0, 1.0], dtype=F64)
    slow = REF.render_reference(*(scene[k] for k in NAMES), view, sh_degree=3, background=background)
    view32 = G.View(view.R.float(), view.t.float(), view.fx, view.fy, view.cx, view.cy, view.width,
                    view.height)
    fast = RZ.render(*(scene[k].float() for k in NAMES), view32, sh_degree=3, background=background.float())
    assert fast.image.dtype == torch.float32
    assert (fast.image.double() - slow).abs().max() < 1e-3


# --- the math underneath -----------------------------------------------------------------------------------
def test_covariance_is_r_s_s_t_r_t_with_the_reference_rotation():
    quats = torch.randn(50, 4, dtype=F64)
    log_scales = torch.randn(50, 3, dtype=F64)
    R = G.quaternion_rotations(quats)
    for i in range(50):
        np.testing.assert_allclose(R[i].numpy(), REF.rotation_reference(quats[i]).numpy(), atol=1e-12)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=F64).expand(50, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(50, dtype=F64))
    sigma = G.covariances(log_scales, quats)
    eigen = torch.linalg.eigvalsh(sigma)
    assert torch.allclose(eigen, torch.sort(torch.exp(2 * log_scales), dim=1).values, rtol=1e-9)


def test_spherical_harmonics_are_orthonormal_on_the_sphere():
    """Gauss-Legendre in cos(theta) times equal steps in phi integrates these degree <= 6 products exactly."""
    nodes, weights = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * 2 * np.pi / 16
    z = np.repeat(nodes, 16)
    w = np.repeat(weights, 16) * 2 * np.pi / 16
    rho = np.sqrt(1 - z**2)
    directions = np.stack([rho * np.cos(np.tile(phi, 8)), rho * np.sin(np.tile(phi, 8)), z], axis=1)
    Y = sh_basis(torch.as_tensor(directions), 3).numpy()
    np.testing.assert_allclose(Y.T @ (w[:, None] * Y), np.eye(16), atol=1e-12)
    np.testing.assert_allclose(Y[:, 0], C0)


def test_colour_is_clamped_at_zero_with_no_gradient_there():
    sh = torch.zeros(2, 1, 3, dtype=F64)
    sh[0, 0, 0] = -10.0
    sh.requires_grad_(True)
    colours = sh_colors(sh, torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=F64), 0)
    colours.sum().backward()
    assert colours[0, 0] == 0 and colours[1, 0] == 0.5
    assert sh.grad[0, 0, 0] == 0 and sh.grad[1, 0, 0] == pytest.approx(C0)


def test_projection_matches_the_per_gaussian_reference():
    scene = random_scene(6)
    view = camera()
    fast = G.project(scene["means"], scene["log_scales"], scene["quats"], view)
    for i in range(len(scene["means"])):
        one = REF.project_one_reference(scene["means"][i], scene["log_scales"][i], scene["quats"][i], view)
        assert int(fast.radii[i]) == one.radius, i
        if one.drawn:
            assert tuple(fast.rects[i].tolist()) == one.rect
            np.testing.assert_allclose(fast.means2d[i].numpy(), one.mean2d.numpy(), atol=1e-10)
            np.testing.assert_allclose(fast.conics[i].numpy(), one.conic.numpy(), rtol=1e-9, atol=1e-12)
    assert int(fast.radii[0]) == 0 and int(fast.radii[1]) == 0


def test_binning_lists_each_gaussian_in_its_tiles_nearest_first():
    rects = np.array([[0, 0, 2, 1], [1, 0, 3, 2], [0, 0, 0, 0], [2, 1, 3, 2]])
    depths = np.array([3.0, 1.0, 0.5, 2.0])
    binning = RZ.bin_gaussians(rects, depths, width=40, height=20, tile_size=16)
    assert (binning.tiles_x, binning.tiles_y) == (3, 2)
    lists = [binning.ids[a:b].tolist() for a, b in binning.ranges]
    assert lists == [[0], [1, 0], [1], [], [1], [1, 3]]
    assert binning.pairs == 2 + 4 + 1
    tied = RZ.bin_gaussians(rects, np.array([1.0, 1.0, 0.5, 1.0]), width=40, height=20, tile_size=16)
    assert [tied.ids[a:b].tolist() for a, b in tied.ranges] == [[0], [0, 1], [1], [], [1], [1, 3]]


def test_binning_with_footprints_leaves_out_only_tiles_the_ellipse_misses():
    """Culled binning keeps a Gaussian in every tile where some pixel centre lies in the ellipse where its
    alpha can reach 1/255 (brute force over the pixels), in the same depth order; the others it keeps are
    those whose ellipse passes between the tile's pixel centres (it tests the box they span), few."""
    rng = np.random.default_rng(3)
    count, width, height, size = 60, 70, 50, 8
    means2d = rng.uniform(-10, 80, (count, 2))
    L = rng.normal(size=(count, 2, 2)) * rng.uniform(0.1, 0.8, (count, 1, 1))
    cov = np.linalg.inv(L @ L.transpose(0, 2, 1) + 0.05 * np.eye(2))
    conics = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], axis=1)
    opacities = rng.uniform(0.001, 1.0, count)
    radius = np.ceil(3 * np.sqrt(np.linalg.eigvalsh(np.linalg.inv(cov))[:, 1]))
    tiles = np.array([-(-width // size), -(-height // size)])
    low = np.clip(np.floor((means2d - radius[:, None]) / size), 0, tiles)
    high = np.clip(np.floor((means2d + radius[:, None] + size - 1) / size), 0, tiles)
    rects = np.concatenate([low, high], axis=1).astype(np.int64)
    depths = rng.uniform(1, 5, count)
    full = RZ.bin_gaussians(rects, depths, width=width, height=height, tile_size=size)
    culled = RZ.bin_gaussians(rects, depths, width=width, height=height, tile_size=size,
                              footprints=(means2d, conics, opacities))
    limit = 2 * np.log(255 * opacities)

    def reach(listed: np.ndarray, tx: int, ty: int, step: float) -> np.ndarray:
        """Whether each Gaussian's ellipse holds a point of the tile's box on a grid of ``step`` px."""
        xs = np.arange(tx * size, min(width, (tx + 1) * size) - 1 + 1e-9, step)
        ys = np.arange(ty * size, min(height, (ty + 1) * size) - 1 + 1e-9, step)
        dx = means2d[listed, 0, None, None] - xs[None, None, :]
        dy = means2d[listed, 1, None, None] - ys[None, :, None]
        q = (conics[listed, 0, None, None] * dx * dx + 2 * conics[listed, 1, None, None] * dx * dy
             + conics[listed, 2, None, None] * dy * dy)
        return (q <= limit[listed, None, None]).any(axis=(1, 2))

    dropped = extra = 0
    for tile, ((a, b), (c, d)) in enumerate(zip(full.ranges, culled.ranges, strict=True)):
        ty, tx = divmod(tile, int(tiles[0]))
        listed, kept = full.ids[a:b], culled.ids[c:d]
        reached = reach(listed, tx, ty, 1.0)
        assert set(listed[reached]) <= set(kept) <= set(listed), tile
        assert kept.tolist() == [g for g in listed if g in set(kept)]          # the depth order kept
        between = np.isin(listed, kept) & ~reached
        assert reach(listed[between], tx, ty, 1 / 16).all(), tile
        dropped += len(listed) - len(kept)
        extra += int(between.sum())
    assert dropped > 20 and extra <= 0.1 * culled.pairs and culled.pairs == full.pairs - dropped


def test_more_gaussians_than_the_cap_are_refused_by_name_before_rendering(monkeypatch):
    scene = random_scene(0, count=12)
    monkeypatch.setattr("lab.modules.splatting.values.MAX_GAUSSIANS", 11)
    with pytest.raises(CapacityExceeded, match="12 Gaussians is more than the cap of 11") as caught:
        RZ.render(*(scene[k] for k in NAMES), camera(), sh_degree=0, background=torch.ones(3, dtype=F64))
    assert caught.value.field == "gaussians"
    monkeypatch.setattr("lab.modules.splatting.values.MAX_GAUSSIANS", 12)
    RZ.render(*(scene[k] for k in NAMES), camera(), sh_degree=0, background=torch.ones(3, dtype=F64))


def test_too_many_tile_pairs_are_refused_by_name(monkeypatch):
    monkeypatch.setattr(RZ, "MAX_TILE_PAIRS", 5)
    with pytest.raises(CapacityExceeded, match="Gaussian, tile"):
        RZ.bin_gaussians(np.array([[0, 0, 3, 2]]), np.ones(1), width=48, height=32, tile_size=16)


def test_row_span_holds_every_pixel_of_the_ellipse_and_little_more():
    """The chord of each row (widened to whole pixels) holds every pixel inside the ellipse, and at most one
    pixel more on each side; a conic that is not positive definite keeps the whole row."""
    from lab.modules.splatting._kernels import _row_span

    rng = np.random.default_rng(0)
    px = np.arange(-40, 80)
    for _ in range(300):
        mx, my = rng.uniform(-20, 60, 2)
        L = rng.normal(size=(2, 2)) * rng.uniform(0.05, 1.0)
        ca, cb, cc = (L @ L.T + 1e-3 * np.eye(2))[[0, 0, 1], [0, 1, 1]]
        limit = rng.uniform(0.0, 12.0)
        for py in range(-5, 45, 3):
            dx, dy = mx - px, my - py
            inside = px[ca * dx * dx + 2 * cb * dx * dy + cc * dy * dy <= limit]
            first, stop = _row_span(mx, my, ca, cb, cc, limit, py, -40, 80)
            if len(inside):
                assert first <= inside.min() and inside.max() < stop
                assert first >= inside.min() - 1 and stop <= inside.max() + 2
            else:
                assert stop - first <= 2
    assert _row_span(3.0, 3.0, 1.0, 2.0, 1.0, 4.0, 3, 0, 16) == (0, 16)      # not positive definite
    first, stop = _row_span(3.0, 3.0, 1.0, 0.0, 1.0, 4.0, 9, 0, 16)     # a row the circle misses
    assert stop <= first


def test_a_thin_diagonal_gaussian_leaves_the_tiles_its_square_touches_but_its_ellipse_misses():
    """A long thin Gaussian along the image diagonal: its 3-sigma square covers every 8 px tile, its ellipse
    only those near the diagonal. The fast path (which walks only the ellipse's chords) draws and
    differentiates exactly what the reference (every pixel of every listed tile) does, and the off-diagonal
    corner tiles, though listed, stay background."""
    view = G.View(torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64), 30.0, 30.0, 15.5, 15.5, 32, 32)
    quats = torch.tensor([[math.cos(math.pi / 8), 0.0, 0.0, math.sin(math.pi / 8)],
                          [1.0, 0.0, 0.0, 0.0]], dtype=F64)              # 45 degrees about the view axis
    scene = {"means": torch.tensor([[0.0, 0.0, 2.0], [0.3, -0.3, 2.5]], dtype=F64),
             "log_scales": torch.log(torch.tensor([[0.9, 0.02, 0.05], [0.03, 0.03, 0.03]], dtype=F64)),
             "quats": quats, "opacity_logits": torch.tensor([3.0, 1.0], dtype=F64),
             "sh": 0.3 * torch.randn(2, 16, 3, generator=torch.Generator().manual_seed(2), dtype=F64)}
    background = torch.tensor([0.2, 0.4, 0.6], dtype=F64)
    projected = G.project(scene["means"], scene["log_scales"], scene["quats"], view, tile_size=8)
    assert projected.rects[0].tolist() == [0, 0, 4, 4]                 # the square lists all 16 tiles
    (fast_image, fast_grads), (slow_image, slow_grads) = both(scene, view, background, degree=2,
                                                              tile_size=8)
    assert (fast_image - slow_image).abs().max() <= 1e-5
    assert_close_gradients(fast_grads, slow_grads)
    drawn = (fast_image - background).abs().amax(dim=-1) > 0
    assert all(drawn[i, i] for i in range(32))                           # along the diagonal
    assert not drawn[0:8, 24:32].any() and not drawn[24:32, 0:8].any()   # listed corner tiles untouched


def test_the_compositing_exponential_is_exp_to_float64_precision_over_its_range():
    """The written-out exponential of the compositing loop (so that it vectorizes) against exp on the
    exponents an alpha above 1/255 can have, in both dtypes, and outside that range still positive."""
    from lab.modules.splatting._kernels import _exp_nonpositive, kernel_constants

    x = np.concatenate([np.linspace(-5.6, 0.0, 20001), [-0.0, -1e-300, -math.log(255.0)]])
    for dtype, tolerance in ((np.float64, 1e-14), (np.float32, 3e-6)):
        k = kernel_constants(dtype)
        coefficients = tuple(k[7:21])
        got = np.array([_exp_nonpositive(dtype(v), k[6], coefficients) for v in x], np.float64)
        exact = np.exp(x.astype(dtype).astype(np.float64))
        assert np.max(np.abs(got - exact) / exact) < tolerance, dtype
    assert 0.0 < _exp_nonpositive(-20.0, 0.125, tuple(kernel_constants(np.float64)[7:21])) < 1e-7


def test_footprint_half_extents_reach_every_row_and_column_of_the_ellipse():
    """sqrt(limit Sigma_yy) and sqrt(limit Sigma_xx) (widened) bound |dy| and |dx| over the ellipse
    d^T conic d <= limit; a conic that is not positive definite reaches everywhere, a negative limit
    nowhere."""
    from lab.modules.splatting._kernels import footprint_half_extents

    rng = np.random.default_rng(1)
    L = rng.normal(size=(200, 2, 2)) * rng.uniform(0.05, 1.0, (200, 1, 1))
    conic = L @ L.transpose(0, 2, 1) + 1e-3 * np.eye(2)
    limits = rng.uniform(0.0, 12.0, 200)
    reach = footprint_half_extents(conic[:, [0, 0, 1], [0, 1, 1]], limits)
    assert reach.shape == (200, 2)
    angles = np.linspace(0.0, 2 * np.pi, 4001)
    for k in range(200):                        # the ellipse's boundary, sampled densely
        circle = np.stack([np.cos(angles), np.sin(angles)]) * math.sqrt(limits[k])
        boundary = np.linalg.solve(np.linalg.cholesky(conic[k]).T, circle)   # d with d^T C d = limit
        for axis, column in ((1, 0), (0, 1)):                                 # dy: half-height first
            extent = np.abs(boundary[axis]).max()
            assert extent <= reach[k, column] <= extent + 2e-3
    not_definite = footprint_half_extents(np.array([[1.0, 2.0, 1.0], [np.nan, 0.0, 1.0]]), np.ones(2))
    assert np.all(np.isinf(not_definite) & (not_definite > 0))
    assert np.all(footprint_half_extents(np.array([[1.0, 0.0, 1.0]]), np.array([-1.0])) == -np.inf)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_projection_and_colours_are_those_of_the_torch_path(seed):
    """render_image's one compiled pass (no gradients) gives project's means, conics, depths, radii and tile
    rectangles and view_colors' colours on the awkward scenes, and its image is the fast path's."""
    from lab.modules.splatting._kernels import _preprocess_kernel

    scene = random_scene(seed, count=40)
    view = camera(48, 32)
    n = 40
    out = (np.empty((n, 2)), np.empty((n, 3)), np.empty(n), np.empty(n, np.int64), np.empty((n, 4), np.int64),
           np.empty((n, 3)), np.empty(n))
    view_row = np.concatenate([view.R.numpy().reshape(9), view.t.numpy(),
                               [view.fx, view.fy, view.cx, view.cy]])
    arrays = [scene[k].numpy() for k in NAMES]
    for degree in (0, 1, 2, 3):
        _preprocess_kernel(*arrays[:5], degree, RZ.SH_CONSTANTS, view_row, 48, 32, 16, G.NEAR_PLANE,
                           G.DILATION, *out)
        with torch.no_grad():
            projected = G.project(scene["means"], scene["log_scales"], scene["quats"], view)
            colours = G.view_colors(scene["means"], scene["sh"], degree, view)
        drawn = projected.radii.numpy() > 0
        np.testing.assert_allclose(out[0][drawn], projected.means2d.numpy()[drawn], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(out[1][drawn], projected.conics.numpy()[drawn], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(out[2], projected.depths.numpy(), rtol=1e-12)
        np.testing.assert_array_equal(out[3], projected.radii.numpy())
        np.testing.assert_array_equal(out[4], projected.rects.numpy())
        np.testing.assert_allclose(out[5], colours.numpy(), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(out[6], torch.sigmoid(scene["opacity_logits"]).numpy(), rtol=1e-12)
    assert 0 < drawn.sum() < n                        # culled ones among them
    background = np.array([0.2, 0.5, 0.9])
    view32 = G.View(view.R.float(), view.t.float(), view.fx, view.fy, view.cx, view.cy, 48, 32)
    image = RZ.render_image(*(a.astype(np.float32) for a in arrays), view32, sh_degree=3,
                            background=background)
    with torch.no_grad():
        fast = RZ.render(*(scene[k].float() for k in NAMES), view32, sh_degree=3,
                         background=torch.tensor(background, dtype=torch.float32)).image.numpy()
    assert image.dtype == np.float32 and image.shape == (32, 48, 3)
    assert np.abs(image - fast).max() < 1e-5
    assert np.abs(image - background).max() > 0.1
