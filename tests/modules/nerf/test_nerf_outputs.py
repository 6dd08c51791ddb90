"""What NeRF makes of a trained field: the mesh by marching cubes (against an analytic field's exact sphere
and the synthetic object's exact depth), the orbit of novel views, the exports (PLY and GLB re-read by
trimesh, a GIF by imageio) and the 2D warm-up (the encoding beats raw coordinates on a textured image).
Fields here are tiny grids (a few hundred steps) and torch runs on one thread."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from modules.texture_helpers import drive
from scipy.spatial import cKDTree

from lab.core import Curve, Image, ImageSet, InvalidControl, Mesh, open_session
from lab.modules import nerf as N
from lab.modules.nerf import PIPELINE
from lab.modules.nerf.grid import raw_density

torch.set_num_threads(1)

TRAIN = {"method": "grid", "grid_resolution": 48, "iterations": 300, "batch_rays": 512, "budget_seconds": 0.0,
         "preview_every": 300}


@pytest.fixture(scope="module")
def trained():
    """A session of the synthetic object (8 views) with a tiny grid trained, and the true surface points
    (every training pixel that sees the object, back-projected with its exact depth)."""
    session = open_session(PIPELINE, "synthetic_object", {"train_views": 8, "test_views": 1}, seed=0)
    session.run("generate_rays")
    session.run("encode_positions")
    session.run("train_nerf", TRAIN)
    rays = session.state["rays"]
    depth = session.truth["train_depths"].reshape(-1)
    seen = np.isfinite(depth)
    surface = rays.origins[seen] + depth[seen, None] * rays.directions[seen]
    return session, surface


# --- the mesh ---------------------------------------------------------------------------------------------
def _sphere_grid(resolution: int = 40, r0: float = 0.5, level: float = 250.0) -> N.GridCheckpoint:
    """A grid field whose density crosses ``level`` on the sphere |x| = r0 (normalized units), red where
    x > 0 and blue where x < 0 (raw colours +-6), in a scene box of centre (1, 2, 3) and radius 2."""
    axis = np.linspace(-1.0, 1.0, resolution)
    x = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1)
    crossing = raw_density(level)  # grid_density(crossing) = level, where the softplus is about linear
    raw = crossing + 40.0 * (r0 - np.linalg.norm(x, axis=-1))
    sign = np.sign(x[..., 0])[..., None]
    color = np.concatenate([6 * sign, -6 * np.ones_like(sign), -6 * sign], axis=-1)
    bounds = N.SceneBounds(1.0, 7.0, np.array([1.0, 2.0, 3.0]), 2.0)
    return N.GridCheckpoint(raw, color, bounds, np.ones(3))


def test_the_mesh_of_a_field_with_a_known_surface_lies_on_it_in_its_colours():
    model = _sphere_grid()
    result = N.extract_mesh(model, resolution=40, level=250.0)
    mesh = result.mesh
    assert isinstance(mesh, Mesh) and result.vertices == len(mesh.vertices) > 1000
    assert result.faces == len(mesh.faces)
    step = 2 * 2.0 / 39  # the lattice step in world units
    radius = np.linalg.norm(mesh.vertices - model.bounds.center, axis=1)
    np.testing.assert_allclose(radius, 0.5 * 2.0, atol=0.15 * step)  # world units: r0 times the box radius
    side = (mesh.vertices[:, 0] - 1.0) / (0.5 * 2.0)
    red, blue = side > 0.3, side < -0.3
    np.testing.assert_allclose(mesh.vertex_colors[red], np.tile([1, 0, 0], (red.sum(), 1)), atol=0.03)
    np.testing.assert_allclose(mesh.vertex_colors[blue], np.tile([0, 0, 1], (blue.sum(), 1)), atol=0.03)
    with pytest.raises(InvalidControl, match="never crosses 10000") as info:
        N.extract_mesh(model, resolution=16, level=1e4)
    assert info.value.field == "level"


def test_the_mesh_of_a_trained_field_lies_near_the_true_surface(trained):
    session, surface = trained
    record = session.run("extract_mesh", {"resolution": 48})
    mesh = session.state["mesh"]
    assert record.metrics["vertices"] == len(mesh.vertices) > 500
    step = 2 * session.state["bounds"].radius / 47
    to_truth, _ = cKDTree(surface).query(mesh.vertices)
    to_mesh, _ = cKDTree(mesh.vertices).query(surface)
    assert np.median(to_truth) < step and np.median(to_mesh) < step  # accurate and complete, within a voxel
    assert np.mean(to_mesh < 3 * step) > 0.9


def test_the_lattice_of_an_mlp_is_its_density_at_the_lattice_points(trained):
    session, _ = trained
    _, result = drive(N.train_nerf(session.state["rays"], N.EncodingConfig(2, 1), session.state["cameras"],
                                   samples=8, hidden=16, layers=2, batch_rays=64, iterations=2,
                                   rng=np.random.default_rng(0)))
    model = result.model
    sigma = N.density_lattice(model, 9)
    points = N.lattice_points(model.bounds, 9)
    net = N.network_from(model)
    pick = np.array([[0, 0, 0], [8, 1, 4], [3, 7, 2], [4, 4, 4]])
    x = (points[tuple(pick.T)] - model.bounds.center) / model.bounds.radius
    d = torch.nn.functional.normalize(torch.randn(len(pick), 3), dim=1)
    with torch.no_grad():
        expected = net(torch.as_tensor(x, dtype=torch.float32), d)[0].numpy()
    np.testing.assert_allclose(sigma[tuple(pick.T)], expected, rtol=1e-5, atol=1e-7)


def test_mesh_exports_reload_with_trimesh(trained, tmp_path):
    import trimesh

    session, _ = trained
    if "mesh" not in session.state:
        session.run("extract_mesh", {"resolution": 48})
    mesh = session.state["mesh"]
    for fmt in ("ply", "glb"):
        written = PIPELINE.export(fmt).write(session.state, session.metrics, tmp_path / f"object.{fmt}")
        back = trimesh.load(written, force="mesh", process=False)
        assert len(back.vertices) == len(mesh.vertices) and len(back.faces) == len(mesh.faces)
        np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-5)
        colours = np.asarray(back.visual.vertex_colors)[:, :3] / 255.0
        np.testing.assert_allclose(colours, mesh.vertex_colors, atol=1 / 255 + 1e-6)


def test_exports_before_their_step_say_which_step_to_run(tmp_path):
    from lab.core import MissingInput

    for fmt, step in (("ply", "extract_mesh"), ("gif", "render_path")):
        with pytest.raises(MissingInput, match=step):
            PIPELINE.export(fmt).write({}, {}, tmp_path / f"x.{fmt}")


# --- the orbit --------------------------------------------------------------------------------------------
def test_the_orbit_circles_the_centre_at_the_cameras_height_from_camera_zero():
    cameras = N.hemisphere_cameras(9, size=20, distance=3.0, offset=0.0, center=np.array([0.5, -1.0, 2.0]))
    centre = np.array([0.5, -1.0, 2.0])
    path = N.orbit_path(cameras, centre, 12, scale=0.5)
    up = N.mean_up(cameras)
    offsets = cameras.centers - centre
    height = (offsets @ up).mean()
    radius = np.linalg.norm(offsets - (offsets @ up)[:, None] * up, axis=1).mean()
    rel = path.centers - centre
    np.testing.assert_allclose(rel @ up, height, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(rel - (rel @ up)[:, None] * up, axis=1), radius, atol=1e-9)
    forward = path.R[:, 2, :]  # every optical axis passes through the centre
    np.testing.assert_allclose(np.cross(forward, -rel), 0.0, atol=1e-9)
    first = rel[0] - (rel[0] @ up) * up
    zero = offsets[0] - (offsets[0] @ up) * up
    assert np.dot(first, zero) / (np.linalg.norm(first) * np.linalg.norm(zero)) > 1 - 1e-9
    assert (path.width, path.height) == (10, 10) and len(path) == 12


def test_render_path_frames_and_their_gif(trained, tmp_path):
    import imageio.v3 as iio

    session, _ = trained
    record = session.run("render_path", {"frames": 5, "scale": 0.4})
    frames, cameras = session.state["path_frames"], session.state["path_cameras"]
    assert isinstance(frames, ImageSet) and len(frames) == 5 and frames[0].pixels.shape == (40, 40, 3)
    assert cameras.image == "path_frames" and len(cameras) == 5 and record.metrics["render_seconds"] > 0
    assert not np.allclose(frames[0].pixels, frames[2].pixels)  # the object turns
    assert frames[0].pixels.min() < 0.5 and frames[0].pixels.max() > 0.9  # the object on white
    written = PIPELINE.export("gif").write(session.state, session.metrics, tmp_path / "orbit.gif")
    back = iio.imread(written, index=None)
    assert back.shape[:3] == (5, 40, 40)


# --- the 2D warm-up ---------------------------------------------------------------------------------------
def test_the_warm_up_fits_a_textured_image_much_better_with_the_encoding():
    from skimage.data import astronaut

    image = Image(astronaut().astype(np.float32) / 255.0, name="astronaut")
    snapshots, result = drive(N.fit_image_2d(ImageSet((image,)), side=40, frequencies=(2, 4, 6),
                                             iterations=200, rng=np.random.default_rng(0)))
    curve = result.fit_psnr
    assert isinstance(curve, Curve) and curve.y.shape == (4, 200)
    assert curve.labels == ("no encoding", "L = 2", "L = 4", "L = 6")
    assert snapshots[-1].iteration == snapshots[-1].total == 800
    assert len(result.fit_images) == 5 and result.fit_images[0].pixels.shape == (40, 40, 3)
    assert result.psnr_with_encoding > result.psnr_without_encoding + 5.0  # a clear margin
    assert curve.y[3, -1] > curve.y[1, -1] > curve.y[0, -1]  # more frequencies, more detail
    assert result.psnr_without_encoding == curve.y[0, -1]


def test_the_warm_up_names_a_view_it_does_not_have():
    image = Image(np.zeros((8, 8, 3), np.float32))
    with pytest.raises(InvalidControl) as info:
        drive(N.fit_image_2d(ImageSet((image,)), view=1, rng=np.random.default_rng(0)))
    assert info.value.field == "view"


def test_vision_lab_export_nerf_ply_trains_and_writes_the_mesh(tmp_path):
    import trimesh
    from typer.testing import CliRunner

    from lab import cli

    out = tmp_path / "object.ply"
    args = ["export", "nerf", "--format", "ply", "--out", str(out), "--option", "train_views=4", "--option",
            "test_views=1", "--set", "train_nerf.method=grid", "--set", "train_nerf.grid_resolution=32",
            "--set", "train_nerf.iterations=80", "--set", "train_nerf.batch_rays=512",
            "--set", "extract_mesh.resolution=24", "--set", "extract_mesh.level=1"]
    result = CliRunner().invoke(cli.app, args, prog_name="vision-lab")
    assert result.exit_code == 0, result.output
    assert "wrote the extracted mesh" in result.stdout
    assert len(trimesh.load(out, process=False).vertices) > 100
