"""lab.modules.nerf's accelerated variant: packed rendering against the dense one, the grid's trilinear
interpolation against known answers, occupancy, and a tiny grid training run through the steps."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lab.core import open_session
from lab.modules import nerf as N
from lab.modules.nerf import PIPELINE

torch.set_num_threads(1)


def test_packed_rendering_matches_dense_rendering_with_empty_samples_left_out():
    rng = np.random.default_rng(0)
    rays, samples = 12, 20
    t = torch.as_tensor(np.sort(rng.uniform(2.0, 6.0, (rays, samples)), axis=1))
    sigma = torch.as_tensor(rng.exponential(1.5, (rays, samples)))
    keep = torch.as_tensor(rng.uniform(0, 1, (rays, samples)) < 0.6)
    keep[4] = False  # a ray with no sample left: the background shows
    sigma = torch.where(keep, sigma, 0.0)
    rgb = torch.as_tensor(rng.uniform(0, 1, (rays, samples, 3)))
    norm = torch.as_tensor(rng.uniform(0.9, 1.3, rays))
    background = torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64)
    dense = N.volume_render(sigma, rgb, t, far=6.0, direction_norm=norm, background=background)
    delta = N.interval_lengths(t, 6.0, norm)
    ray, _ = keep.nonzero(as_tuple=True)
    packed = N.volume_render_packed(sigma[keep], rgb[keep], t[keep], delta[keep], ray, rays, far=6.0,
                                    background=background)
    np.testing.assert_allclose(packed.color.numpy(), dense.color.numpy(), rtol=1e-10)
    np.testing.assert_allclose(packed.opacity.numpy(), dense.opacity.numpy(), rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(packed.depth.numpy(), dense.depth.numpy(), rtol=1e-10)
    np.testing.assert_allclose(packed.weights.numpy(), dense.weights[keep].numpy(), rtol=1e-10)
    np.testing.assert_allclose(packed.color[4].numpy(), background.numpy())


def _linear_field(resolution: int) -> tuple[N.GridField, np.ndarray]:
    """A grid whose vertex values are ``a . x + b`` (trilinear interpolation reproduces it exactly)."""
    a = np.array([0.3, -0.7, 1.1])
    axis = np.linspace(-1.0, 1.0, resolution)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    values = torch.as_tensor(a[0] * x + a[1] * y + a[2] * z + 0.2, dtype=torch.float32)
    return N.GridField(resolution, values, torch.stack([values] * 3, dim=-1)), a


def test_trilinear_interpolation_reproduces_a_linear_function_on_both_paths():
    field, a = _linear_field(9)
    points = torch.as_tensor(np.random.default_rng(1).uniform(-1, 1, (200, 3)), dtype=torch.float32)
    expected = points.double().numpy() @ a + 0.2
    rows, weights = field.corners(points)
    np.testing.assert_allclose(weights.sum(dim=1).numpy(), 1.0, atol=1e-6)
    with torch.no_grad():  # embedding_bag
        got = field.sample(field.density, rows, weights)[:, 0]
        np.testing.assert_allclose(got.numpy(), expected, atol=1e-5)
    with_grad = field.sample(field.color, rows, weights)  # index_select, and its gradient
    np.testing.assert_allclose(with_grad[:, 1].detach().numpy(), expected, atol=1e-5)
    with_grad.sum().backward()
    assert field.table.grad is not None
    assert float(field.table.grad[:, 1:].sum()) == pytest.approx(600.0, rel=1e-5)
    assert float(field.table.grad[:, 0].abs().sum()) == 0.0
    finer = field.upsampled(17)
    rows, weights = finer.corners(points)
    with torch.no_grad():
        got = finer.sample(finer.density, rows, weights)[:, 0]
        np.testing.assert_allclose(got.numpy(), expected, atol=1e-5)


def test_occupancy_marks_dense_cells_and_their_neighbours_only():
    field = N.GridField(8, torch.full((8, 8, 8), -20.0))
    with torch.no_grad():
        field.density.view(8, 8, 8)[3, 4, 5] = 10.0
    occupied = field.occupancy().cells
    assert occupied[2:5, 3:6, 4:7].all() and int(occupied.sum()) == 27


def test_grid_skips_empty_space_and_stops_behind_a_wall():
    """An opaque slab at x in [0, 0.25] of the box: rays along +x evaluate only samples near it, see it."""
    r = 17
    raw = torch.full((r, r, r), -20.0)
    raw[8:11] = N.grid.raw_density(550.0)  # vertices at x = 0, 0.125, 0.25: sigma = 550
    field = N.GridField(r, raw, torch.zeros(r, r, r, 3))
    bounds = N.SceneBounds(1.0, 3.0, np.zeros(3), 1.0)
    origins = torch.tensor([[-2.0, 0.1 * k - 0.3, 0.05] for k in range(7)])
    directions = torch.tensor([[1.0, 0.0, 0.0]] * 7)
    with torch.no_grad():
        out, t = N.render_grid(field, origins, directions, bounds, step=1.0 / (r - 1),
                               background=torch.ones(3), occupied=field.occupancy())
    # what early termination drops (samples of weight < SKIP_BELOW) is below 1e-4 in all
    np.testing.assert_allclose(out.opacity.numpy(), 1.0, atol=1e-4)
    np.testing.assert_allclose(out.color.numpy(), 0.5, atol=1e-4)  # sigmoid(0)
    np.testing.assert_allclose(out.depth.numpy(), 1.94, atol=0.07)  # the wall's face at x = -0.06 .. 0
    # of the 32 steps from near to far, 2 per ray are evaluated: at the face (empty cells skipped before it,
    # the dilated cell's samples of no weight left out, the rest terminated behind it)
    assert len(t) == 7 * 2 and float(t.min()) > 1.85 and float(t.max()) < 2.2


def test_a_tiny_grid_run_through_the_steps():
    session = open_session(PIPELINE, "synthetic_object", {"train_views": 3, "test_views": 1}, seed=1)
    session.run("generate_rays")
    session.run("encode_positions")
    record = session.run("train_nerf", {"method": "grid", "grid_resolution": 24, "batch_rays": 512,
                                        "iterations": 40, "preview_every": 20})
    assert record.status == "ok", record.error
    model = session.state["model"]
    assert isinstance(model, N.GridCheckpoint) and model.resolution == 24
    curve = session.state["loss_curve"].y[0]
    assert curve[-1] < 0.5 * curve[0]
    assert 0 < record.metrics["samples_per_ray"] < 40
    held = session.run("render_held_out")
    assert held.status == "ok" and held.metrics["psnr"] > 12
    view = session.run("render_view")
    assert view.status == "ok" and session.state["rendered"].pixels.shape == (100, 100, 3)


@pytest.mark.parametrize("jittered", [False, True])
def test_two_level_candidates_equal_checking_every_step(jittered):
    """A sparse occupancy (a few blobs, one at the box's edge) and rays from every side: the same samples."""
    from lab.modules.nerf.grid import Occupancy, grid_candidates
    from lab.modules.nerf.reference import grid_candidates_reference

    rng = np.random.default_rng(3)
    r = 20
    occupied = torch.zeros((r, r, r), dtype=torch.bool)
    for i, j, k in rng.integers(0, r, (6, 3)):
        occupied[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2, max(k - 1, 0):k + 2] = True
    occupied[r - 1, 5:8, 5:8] = True
    bounds = N.SceneBounds(1.5, 4.5, np.zeros(3), 1.0)
    directions = torch.as_tensor(rng.normal(0, 1, (300, 3)), dtype=torch.float32)
    lengths = torch.as_tensor(rng.uniform(0.8, 1.0, (300, 1)), dtype=torch.float32)
    directions = directions / (directions.norm(dim=1, keepdim=True) * lengths)
    origins = -3.0 * directions / directions.norm(dim=1, keepdim=True) \
        + torch.as_tensor(rng.normal(0, 0.3, (300, 3)), dtype=torch.float32)
    jitter = torch.as_tensor(rng.uniform(0, 1, (300, 1)), dtype=torch.float32) if jittered else None
    fast = grid_candidates(origins, directions, bounds, 1.0 / (r - 1), Occupancy.of(occupied, 1.0 / (r - 1)),
                           jitter)
    slow = grid_candidates_reference(origins, directions, bounds, 1.0 / (r - 1), occupied, jitter)
    assert len(slow[0]) > 100
    for a, b in zip(fast, slow, strict=True):
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-5, atol=1e-5)


def _random_scene(r: int = 12, rays: int = 200, seed: int = 0):
    """A random grid with a sparse occupancy and rays through the box from one side, jittered."""
    generator = torch.Generator().manual_seed(seed)
    raw = torch.randn((r, r, r), generator=generator) * 3.0 + 12.0
    raw[:, :, : r // 3] = -20.0  # the front third (rays go along +z) is empty space
    field = N.GridField(r, raw, torch.randn((r ** 3, 3), generator=generator))
    bounds = N.SceneBounds(2.0, 4.0, np.array([0.1, -0.1, 0.0]), 1.0)
    origins = torch.randn((rays, 3), generator=generator) * 0.1 + torch.tensor([0.0, 0.0, -3.0])
    directions = torch.randn((rays, 3), generator=generator) * 0.2 + torch.tensor([0.0, 0.0, 1.0])
    jitter = torch.rand((rays, 1), generator=generator)
    return field, bounds, origins, directions, jitter


@pytest.mark.parametrize("stop", [0.0, 0.05])
def test_compiled_composite_matches_the_reference_loop(stop):
    from lab.modules.nerf.grid import GridMarch, composite_grid, grid_step
    from lab.modules.nerf.reference import composite_grid_reference

    field, bounds, origins, directions, jitter = _random_scene()
    background = torch.tensor([1.0, 0.5, 0.2])
    occupied = field.occupancy()
    assert 0 < int(occupied.cells.sum()) < occupied.cells.numel()
    march = GridMarch.of(field, origins, directions, bounds, background=background, occupied=occupied,
                         jitter=jitter, stop=stop)
    fast = composite_grid(field, march, threads=2)
    r = field.resolution
    slow = composite_grid_reference(field.density.detach().numpy().reshape(r, r, r),
                                    field.color.detach().numpy().reshape(r, r, r, 3), occupied.cells.numpy(),
                                    origins.numpy(), directions.numpy(), jitter.numpy()[:, 0], bounds,
                                    grid_step(field), stop, background.numpy())
    assert slow["samples"].mean() > 3 and (stop == 0.0 or slow["opacity"].max() >= 1.0 - stop)
    np.testing.assert_allclose(fast.color.numpy(), slow["color"], atol=2e-5)
    np.testing.assert_allclose(fast.depth.numpy(), slow["depth"], atol=1e-4)
    np.testing.assert_allclose(fast.opacity.numpy(), slow["opacity"], atol=2e-5)
    np.testing.assert_array_equal(fast.weights.numpy(), slow["samples"])


def test_compiled_composite_stops_early_within_its_threshold_and_its_gradient_is_autograds():
    """Early termination changes a colour by at most the transmittance left; the compiled backward pass
    equals torch's autograd through the vectorized path (candidates, trilinear gathers, packed rendering)."""
    from lab.modules.nerf.grid import (CompositeGrid, GridMarch, composite_grid, grid_candidates,
                                       grid_density, grid_step)

    field, bounds, origins, directions, jitter = _random_scene(seed=1)
    background = torch.tensor([1.0, 0.5, 0.2])
    occupied = field.occupancy()
    every = composite_grid(field, GridMarch.of(field, origins, directions, bounds, background=background,
                                               occupied=occupied, jitter=jitter, stop=0.0))
    early = composite_grid(field, GridMarch.of(field, origins, directions, bounds, background=background,
                                               occupied=occupied, jitter=jitter, stop=0.01))
    assert int(early.weights.sum()) < 0.8 * int(every.weights.sum())
    assert float((early.color - every.color).abs().max()) <= 0.01
    # the gradient, without early termination, against autograd
    march = GridMarch.of(field, origins, directions, bounds, background=background, occupied=occupied,
                         jitter=jitter, stop=0.0)
    upstream = torch.randn((len(origins), 3), generator=torch.Generator().manual_seed(2))
    table = field.table.detach().clone().requires_grad_()
    color, _ = CompositeGrid.apply(table, field, march)
    (color * upstream).sum().backward()
    ray, t, x, delta = grid_candidates(origins, directions, bounds, grid_step(field), occupied, jitter)
    rows, weights = field.corners(x)
    sigma = grid_density(field.sample(field.density, rows, weights)[:, 0])
    rgb = torch.sigmoid(field.sample(field.color, rows, weights))
    oracle = N.volume_render_packed(sigma, rgb, t, delta, ray, len(origins), far=bounds.far,
                                    background=background)
    np.testing.assert_allclose(color.detach().numpy(), oracle.color.detach().numpy(), atol=1e-5)
    (oracle.color * upstream).sum().backward()
    assert field.table.grad is not None and float(field.table.grad.abs().max()) > 0.01
    np.testing.assert_allclose(table.grad.numpy(), field.table.grad.numpy(), atol=1e-5)


def test_supersampled_training_rays_are_the_rays_through_the_renderers_subpixel_points():
    """pixel_axes read off generate_rays' bundle (non-square pixels, a shifted principal point) move each
    pixel's centre ray to exactly the rays camera_rays casts through the points of subpixel_offsets, which
    are the shared renderer's supersampling points ((c + 0.5) / s - 0.5)."""
    from lab.core import Cameras, InvalidValue
    from lab.modules.nerf.grid import pixel_axes, subpixel_offsets

    assert np.allclose(subpixel_offsets(2), [[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]])
    assert np.allclose(subpixel_offsets(1), [[0.0, 0.0]])
    cams = N.hemisphere_cameras(2, size=8, distance=3.0, offset=0.0, center=np.zeros(3))
    K = cams.K.copy()
    K[:, 1, 1] *= 1.3
    K[:, 0, 2] += 0.7
    cams = Cameras(K, cams.R, cams.t, 8, 6)
    origins, directions = N.cameras_rays(cams)
    views = np.repeat(np.arange(2), 48)
    bundle = N.RayBundle(origins.reshape(-1, 3).numpy(), directions.reshape(-1, 3).numpy(),
                         np.zeros((96, 3)), views, N.SceneBounds(2.0, 4.0, np.zeros(3), 1.0))
    axes = pixel_axes(bundle)                                                       # (2, 2, 3)
    centres = N.pixel_centres(8, 6).numpy()
    for du, dv in subpixel_offsets(2):
        _, exact = N.camera_rays(cams.K, cams.R, cams.t, centres + np.array([du, dv]))
        moved = directions.numpy() + du * axes[:, None, 0] + dv * axes[:, None, 1]
        assert np.allclose(moved, exact.numpy(), atol=1e-6)
    shuffled = np.random.default_rng(0).permutation(48)
    with pytest.raises(InvalidValue, match="pixel grid"):
        pixel_axes(N.RayBundle(bundle.origins[:48], bundle.directions[shuffled], np.zeros((48, 3)),
                               np.zeros(48), bundle.bounds))


def test_box_filtering_a_rendering_averages_its_blocks():
    from lab.core import InvalidValue
    from lab.modules.nerf.model import ImageRendering

    rng = np.random.default_rng(1)
    fine = ImageRendering(rng.random((4, 6, 3)).astype(np.float32), rng.random((4, 6)).astype(np.float32),
                          rng.random((4, 6)).astype(np.float32))
    coarse = fine.box_filtered(2)
    assert coarse.color.shape == (2, 3, 3) and coarse.depth.shape == (2, 3)
    assert np.isclose(coarse.color[1, 2, 0], fine.color[2:4, 4:6, 0].mean())
    assert np.isclose(coarse.opacity[0, 1], fine.opacity[0:2, 2:4].mean())
    assert fine.box_filtered(1).color is not None and np.allclose(fine.box_filtered(1).depth, fine.depth)
    with pytest.raises(InvalidValue, match="3x3 blocks"):
        fine.box_filtered(3)


def test_total_variation_is_the_mean_gradient_norm_of_forward_differences():
    """total_variation at every vertex against a loop over vertices (the last face's vertices take the
    differences of the face before), and its gradient pulls a spike towards its neighbours."""
    from lab.modules.nerf.grid import total_variation

    r = 5
    values = np.random.default_rng(4).normal(0, 2, (r, r, r, 4))
    field = N.GridField(r, torch.as_tensor(values[..., 0], dtype=torch.float32),
                        torch.as_tensor(values[..., 1:], dtype=torch.float32))
    tv_sigma, tv_rgb = (v.detach() for v in total_variation(field, torch.arange(r ** 3)))
    norms = []
    for i in range(r):
        for j in range(r):
            for k in range(r):
                a, b, c = min(i, r - 2), min(j, r - 2), min(k, r - 2)
                here = values[a, b, c]
                steps = np.stack([values[a + 1, b, c], values[a, b + 1, c], values[a, b, c + 1]]) - here
                norms.append(np.sqrt((steps ** 2).sum(axis=0) + 1e-8))
    norms = np.array(norms)
    assert float(tv_sigma) == pytest.approx(norms[:, 0].mean(), rel=1e-5)
    assert float(tv_rgb) == pytest.approx(norms[:, 1:].sum(axis=1).mean(), rel=1e-5)
    spike = N.GridField(r, torch.zeros(r, r, r), torch.zeros(r, r, r, 3))
    with torch.no_grad():
        spike.table[(2 * r + 2) * r + 2, 0] = 5.0
    total_variation(spike, torch.arange(r ** 3))[0].backward()
    assert spike.table.grad is not None and float(spike.table.grad[(2 * r + 2) * r + 2, 0]) > 0
    assert float(spike.table.grad[:, 1:].abs().sum()) == 0.0
