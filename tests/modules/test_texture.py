"""The texture module as a whole: its registration, pipeline, views and datasets, the metrics and the mesh.

The parts have their own files: test_texture_efros_leung.py (the lesson's window distance, the fast
Efros–Leung against the slow reference), test_texture_quilting.py (the minimum-error cut against brute
force, quilting and transfer), test_texture_parametric.py (Heeger–Bergen). Everything runs on small images
so that each file takes seconds.
"""

import numpy as np
import pytest

from lab.core import Image, InvalidValue, Mesh, open_session
from lab.data.textures import brick, grass, gravel, image_file, procedural_pixels, transfer_target
from lab.modules import MODULES, get_pipeline
from lab.modules.texture import (PIPELINE, VIEWS, parametric_surface, sample_texture, seam_score,
                                 texture_statistics_distance, textured_trimesh, wrap_on_mesh)

STEPS = [spec.name for spec in PIPELINE.steps]


# ----------------------------------------------------------------------------------------------------
# Registration, the pipeline and its views
# ----------------------------------------------------------------------------------------------------
def test_module_is_registered_with_its_steps_and_datasets():
    assert "texture" in MODULES and get_pipeline("texture") is PIPELINE
    assert STEPS[:6] == ["pick_query_window", "window_distances", "match_window", "pick_overlap",
                         "min_error_cut", "join_blocks"]
    assert {"synthesize_parametric", "synthesize_efros_leung", "quilt", "transfer_texture",
            "wrap_on_mesh"} <= set(STEPS)
    assert [d.name for d in PIPELINE.datasets] == ["brick", "grass", "gravel", "procedural", "image_file"]
    for name in ("synthesize_parametric", "synthesize_efros_leung", "quilt", "transfer_texture"):
        assert PIPELINE.step(name).is_generator
    window = PIPELINE.step("synthesize_efros_leung").control("window")
    assert (window.minimum, window.maximum, window.default) == (3, 31, 11)
    assert PIPELINE.step("quilt").control("mode").choices == ("random", "best_overlap", "min_cut")
    assert PIPELINE.dataset("image_file").takes_path


def test_every_step_runs_on_a_small_procedural_sample():
    session = open_session(PIPELINE, "procedural", {"size": 24, "colour": True, "target_size": 24}, seed=3)
    params = {"synthesize_parametric": {"size": (24, 24), "levels": 2},
              "synthesize_efros_leung": {"size": (12, 12), "window": 5},
              "quilt": {"size": (32, 32), "block": 12, "overlap": 3},
              "transfer_texture": {"block": 9}, "wrap_on_mesh": {"resolution": 8}}
    for name in STEPS:
        record = session.run(name, params.get(name))
        assert record.status == "ok"
    assert session.state["parametric"].pixels.shape == (24, 24, 3)
    assert session.state["efros_leung"].pixels.shape == (12, 12, 3)
    assert session.state["quilting"].pixels.shape == (32, 32, 3)
    assert session.state["transferred"].pixels.shape == (24, 24, 3)
    assert isinstance(session.state["textured_mesh"], Mesh)
    assert session.metrics["match_window"]["match_error_px"] == 0.0
    for name in ("synthesize_parametric", "synthesize_efros_leung", "quilt"):
        assert 0.0 <= session.metrics[name]["stat_distance"] < 2.0
        assert abs(session.metrics[name]["mean_error"]) < 0.1  # procedural truth: mean 0.5


def test_every_name_the_viewer_reads_is_made_by_a_step_or_a_dataset():
    from lab.viewer.interactions.texture import TEXTURES

    made = {name for spec in PIPELINE.steps for name in spec.writes}
    for dataset in ("brick", "procedural"):
        made |= set(PIPELINE.dataset(dataset).load({"size": 16} if dataset == "procedural" else {}).state)
    assert PIPELINE.views == frozenset(VIEWS)
    assert set(VIEWS) <= made, sorted(set(VIEWS) - made)
    assert set(TEXTURES) <= PIPELINE.views  # the textures the mesh viewer may wrap
    assert {"efros_leung_trace", "quilting_layout"} <= PIPELINE.views  # the growth and quilt explorers


# ----------------------------------------------------------------------------------------------------
# The datasets
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("loader", [brick, grass, gravel])
def test_skimage_textures_load_offline_as_gray_samples(loader):
    loaded = loader(size=32, downsample=4, target_size=24)
    assert loaded.state["sample"].pixels.shape == (32, 32)
    assert loaded.state["transfer_target"].pixels.shape == (24, 24)
    assert 0.05 < loaded.state["sample"].pixels.std() < 0.5


@pytest.mark.parametrize("pattern", ["noise", "blobs", "stripes", "dots"])
def test_procedural_textures_have_their_known_statistics(pattern):
    pixels, truth = procedural_pixels(pattern, 256, np.random.default_rng(1))
    assert abs(pixels.mean() - truth["mean"]) < 0.03
    assert abs(pixels.std() / truth["std"] - 1.0) < 0.12


def test_image_file_dataset_reads_shrinks_and_matches_the_target_kind(tmp_path):
    import cv2

    rgb = (np.random.default_rng(0).random((40, 60, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "t.png"), rgb)
    loaded = image_file(path=str(tmp_path / "t.png"), max_size=30)
    assert loaded.state["sample"].pixels.shape == (20, 30, 3)
    assert loaded.state["transfer_target"].pixels.ndim == 3
    with pytest.raises(InvalidValue, match="no image file"):
        image_file(path=str(tmp_path / "missing.png"))
    assert transfer_target("rings", 16, colour=False).pixels.shape == (16, 16)


# ----------------------------------------------------------------------------------------------------
# Metrics
# ----------------------------------------------------------------------------------------------------
def test_statistics_distance_is_small_for_the_same_process_and_large_for_another():
    a = procedural_pixels("stripes", 64, np.random.default_rng(0))[0]
    b = procedural_pixels("stripes", 64, np.random.default_rng(1))[0]
    noise = procedural_pixels("noise", 64, np.random.default_rng(2))[0]
    assert texture_statistics_distance(a, a) == pytest.approx(0.0, abs=1e-12)
    assert texture_statistics_distance(b, a) < 0.25 * texture_statistics_distance(noise, a)
    shifted = np.roll(a, (5, 7), axis=(0, 1))  # translation invariant (statistics, not pixels)
    assert texture_statistics_distance(shifted, a) < 0.1
    with pytest.raises(InvalidValue, match="channel"):
        texture_statistics_distance(np.zeros((16, 16, 3)), a)


def test_seam_score_sees_pasted_edges():
    rng = np.random.default_rng(0)
    sample = procedural_pixels("blobs", 32, rng)[0]
    rows, cols = np.mgrid[0:16, 0:16]
    whole = np.stack([rows + 4, cols + 4], axis=2)
    assert seam_score(sample[4:20, 4:20], whole, sample) == 1.0  # one copy: no seam at all
    halves = whole.copy()
    halves[:, 8:, 0] += 10  # the right half comes from elsewhere
    pasted = sample[halves[..., 0], halves[..., 1]]
    pasted[:, 8:] = 1.0 - pasted[:, 8:]  # and does not agree at all
    assert seam_score(pasted, halves, sample) > 3.0


# ----------------------------------------------------------------------------------------------------
# The mesh
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", ["plane", "cylinder", "torus"])
def test_parametric_surfaces_have_uvs_and_closed_seams(shape):
    vertices, faces, uv = parametric_surface(shape, 8)
    assert vertices.shape == (81, 3) and faces.shape == (128, 3) and uv.shape == (81, 2)
    assert uv.min() == 0.0 and uv.max() == 1.0
    grid = vertices.reshape(9, 9, 3)
    if shape != "plane":  # u = 0 and u = 1 meet
        np.testing.assert_allclose(grid[:, 0], grid[:, -1], atol=1e-12)
    if shape == "torus":
        np.testing.assert_allclose(grid[0], grid[-1], atol=1e-12)
        radii = np.hypot(vertices[:, 0], vertices[:, 1])
        assert radii.min() == pytest.approx(0.6) and radii.max() == pytest.approx(1.4)


def test_wrap_on_mesh_colours_vertices_from_the_texture():
    checker = np.kron([[0.0, 1.0], [1.0, 0.0]], np.ones((8, 8))).astype(np.float32)
    result = wrap_on_mesh(Image(checker), texture="sample", shape="plane", repeats=1, resolution=4)
    colours = result.textured_mesh.vertex_colors.reshape(5, 5, 3)
    assert colours[1, 1, 0] == pytest.approx(0.0) and colours[1, 3, 0] == pytest.approx(1.0)
    np.testing.assert_allclose(sample_texture(checker, np.array([[0.75, 0.25]])), [[1.0, 1.0, 1.0]])
    with pytest.raises(InvalidValue, match="run step 'quilt' first"):
        wrap_on_mesh(Image(checker), texture="quilting")
    with pytest.raises(InvalidValue, match="run step 'transfer_texture' first"):
        wrap_on_mesh(Image(checker), texture="transferred")
    mesh = textured_trimesh(result.textured_mesh, result.mesh_uv, checker)
    assert len(mesh.visual.uv) == 25 and mesh.visual.material.image.size == (16, 16)
