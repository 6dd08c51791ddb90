"""The texture module's viewer interactions: the Efros–Leung growth replayed and a clicked pixel explained
(its window, candidates and the copied window), quilting's overlap error surface and cut, and the
texture wrapped on a mesh. Pure functions first, then the interactions in a ClientView on a small
procedural sample."""

from __future__ import annotations

import numpy as np
import pytest

from lab.core import Image, InvalidValue, Mesh
from lab.data.textures import procedural
from lab.modules.texture import PIPELINE, efros_leung, image_quilting
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.interactions import EXPLORE_ROOT, interactions_for
from lab.viewer.interactions.texture import (CUT_COLOR, INTERACTIONS, GrowthExplorer, MeshViewer, Plane,
                                             QuiltExplorer, available_textures, block_at,
                                             cut_mask, fill_order_image,
                                             growth_frame, mesh_for, overlap_panel, plane_pixel)

OPTIONS = {"pattern": "blobs", "size": 20, "target_size": 24}
EL = {"size": (12, 12), "window": 5}
QUILT = {"size": (30, 30), "block": 10, "overlap": 3}


def sample(size: int = 20) -> Image:
    return procedural(pattern="blobs", size=size, seed=1).state["sample"]


@pytest.fixture
def view(server, store):
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    view.open_session(store.create(PIPELINE, "procedural", OPTIONS))
    return view


def part(view, cls):
    return next(i for i in view.interactions if isinstance(i, cls))


# --- pure functions -------------------------------------------------------------------------------------
def test_interactions_are_found_by_the_pipeline_name():
    assert interactions_for("texture") == INTERACTIONS == [GrowthExplorer, QuiltExplorer, MeshViewer]


def test_plane_pixel_inverts_plane_point_and_rejects_misses():
    plane = Plane((1.0, -2.0, 0.5), 40, 30, 0.05)
    for row, col in [(0, 0), (29, 39), (12, 7)]:
        target = plane.point(row, col)
        origin = target + np.array([0.3, -0.2, 4.0])
        assert plane_pixel(plane, origin, target - origin) == (row, col)
    with pytest.raises(InvalidValue, match="outside"):
        origin = plane.point(0, 45) + np.array([0, 0, 1.0])
        plane_pixel(plane, origin, [0, 0, -1.0])
    with pytest.raises(InvalidValue, match="parallel"):
        plane_pixel(plane, [0, 0, 1.0], [1.0, 0, 0])
    with pytest.raises(InvalidValue, match="behind"):
        plane_pixel(plane, [1.0, -2.0, 1.0], [0, 0, 1.0])


def test_fill_order_and_growth_frames_show_what_was_filled_when():
    texture, trace = efros_leung(sample(), size=(10, 10), window=5, rng=np.random.default_rng(0))
    image = Image(texture)
    first = fill_order_image(trace)
    assert first.shape == (10, 10, 3) and first.dtype == np.uint8
    early = trace.fill_order < 9
    frame = growth_frame(image, trace, 9)
    assert np.all(frame[~early] == (70, 70, 90)) and not np.all(frame[early] == (70, 70, 90))
    assert np.array_equal(growth_frame(image, trace, 100)[..., 0], np.rint(texture * 255).astype(np.uint8))


def test_block_at_and_the_overlap_panel_show_the_cut():
    _pixels, _source, layout = image_quilting(sample(24), size=(24, 24), block=10, overlap=3,
                                              rng=np.random.default_rng(0))
    assert block_at(layout, 0, 0) == 0
    assert block_at(layout, 23, 23) == len(layout.positions) - 1
    panel = overlap_panel(layout, 1)  # the second block overlaps the first on its left
    assert panel.shape[0] >= 200 and (panel == CUT_COLOR).all(axis=2).any()
    cut = cut_mask(layout, 1)
    assert cut[:, :3].any(axis=1).all()  # the cut crosses every row of the left overlap
    with pytest.raises(InvalidValue, match="block"):
        overlap_panel(layout, len(layout.positions))


def test_mesh_for_wraps_the_texture_with_uvs():
    state = {"sample": sample(16)}
    assert available_textures(state) == ["sample"]
    mesh = mesh_for(state, "sample", "torus", 2, resolution=8)
    assert len(mesh.vertices) == 81 and mesh.visual.uv.shape == (81, 2)
    assert mesh.visual.material.baseColorTexture.size == (32, 32)  # tiled twice
    with pytest.raises(Exception, match="run the step"):
        mesh_for(state, "quilting", "plane", 1)


# --- in the viewer --------------------------------------------------------------------------------------
def test_growth_explorer_replays_growth_and_explains_a_clicked_pixel(view):
    explorer = part(view, GrowthExplorer)
    view.run_with("synthesize_efros_leung", EL)
    state = view.session.state
    trace, texture = state["efros_leung_trace"], state["efros_leung"]
    assert explorer.trace is trace and explorer.grown.max == 144 and not explorer.grown.disabled
    frame = explorer.show_growth(20)
    assert (frame.reshape(-1, 3) == (70, 70, 90)).all(axis=1).sum() == 144 - 20
    # a click on the texture plane, through the pixel's centre
    target = explorer.output_plane.point(0, 11)
    matches = explorer.click_output(target + np.array([0, 0, 3.0]), np.array([0, 0, -1.0]))
    assert explorer.pixel == (0, 11)
    assert np.array_equal(matches.chosen + 2, trace.source[0, 11])  # the window it really copied
    assert any(np.array_equal(c, matches.chosen) for c in matches.candidates)
    levels = np.rint(state["sample"].pixels * 255)
    assert np.rint(texture.pixels[0, 11] * 255) == levels[tuple(trace.source[0, 11])]
    names = explorer.scene_nodes()
    assert {"texture", "sample", "window", "candidates", "chosen"} <= set(names)
    assert explorer.ctx.node("efros_leung", "window") == f"{EXPLORE_ROOT}/texture/efros_leung/window"
    assert "candidate window" in explorer.info.content


def test_growth_explorer_survives_a_reset_and_shows_bad_picks(view):
    explorer = part(view, GrowthExplorer)
    view.run_with("synthesize_efros_leung", EL)
    explorer.ctx.guarded(lambda: explorer.pick_pixel(12, 0))()
    assert "outside" in view.errors[-1]
    view.session.reset("synthesize_efros_leung")
    view.refresh(force=True)
    assert explorer.trace is None and explorer.scene_nodes() == [] and explorer.grown.disabled
    explorer.ctx.guarded(lambda: explorer.pick_pixel(0, 0))()
    assert "synthesize_efros_leung" in view.errors[-1]


def test_quilt_explorer_shows_the_overlap_and_cut_of_a_picked_block(view):
    explorer = part(view, QuiltExplorer)
    view.run_with("quilt", QUILT)
    layout = view.session.state["quilting_layout"]
    assert explorer.layout is layout and explorer.block == 1
    index = explorer.pick_pixel(29, 29)
    assert index == len(layout.positions) - 1 and explorer.block == index
    assert explorer.slider.value == index
    assert (explorer.panel.image is not None) and "along the cut" in explorer.info.content
    assert {"quilt", "block"} <= set(explorer.scene_nodes())
    view.session.reset("quilt")
    view.refresh(force=True)
    assert explorer.layout is None and explorer.scene_nodes() == []


def test_mesh_viewer_wraps_the_newest_texture_on_the_chosen_shape(view):
    viewer = part(view, MeshViewer)
    assert viewer.shown is not None and viewer.shown[0] == "sample"  # the sample until a texture is made
    view.run_with("quilt", QUILT)
    assert viewer.shown[0] == "quilting"
    mesh = viewer.show("quilting", "cylinder", 3)
    assert viewer.shown[:3] == ("quilting", "cylinder", 3) and viewer.shape.value == "cylinder"
    assert mesh.visual.material.baseColorTexture.size == (90, 90) and mesh.visual.material.metallicFactor == 0
    assert viewer.scene_nodes() == ["mesh"]
    viewer.ctx.guarded(lambda: viewer.show("quilting", "sphere"))()
    assert "plane, cylinder or torus" in view.errors[-1]
    view.session.reset("quilt")
    view.refresh(force=True)
    assert viewer.shown[0] == "sample"


def test_once_wrap_on_mesh_ran_its_mesh_is_the_only_one_and_the_inputs_show_its_controls(view):
    viewer = part(view, MeshViewer)
    view.run_with("quilt", QUILT)
    assert viewer.scene_nodes() == ["mesh"] and "preview" in viewer.legend()[0].note
    assert "wrap_on_mesh" in viewer.note.content
    np.testing.assert_allclose(viewer.bounds(), [[-1.4, -1.4, -0.4], [1.4, 1.4, 0.4]], atol=1e-6)
    view.run_with("wrap_on_mesh", {"texture": "quilting", "shape": "cylinder", "repeats": 3})
    assert isinstance(view.session.state.get("textured_mesh"), Mesh)
    assert viewer.scene_nodes() == [] and viewer.legend() == [] and viewer.bounds() is None  # one mesh only
    assert (viewer.texture.value, viewer.shape.value, viewer.repeats.value) == ("quilting", "cylinder", 3)
    assert viewer.texture.disabled and viewer.shape.disabled
    assert "quilting on a cylinder, repeated 3x" in viewer.info.content
    viewer.ctx.guarded(lambda: viewer.show("sample", "torus"))()
    assert "wrap_on_mesh" in view.errors[-1]
    view.session.reset("wrap_on_mesh")  # back to the preview, its inputs free again
    view.refresh(force=True)
    assert viewer.scene_nodes() == ["mesh"] and not viewer.texture.disabled


def test_the_scene_rows_do_not_overlap_and_each_drawing_is_in_the_legend(view):
    view.run_with("synthesize_efros_leung", EL)
    view.run_with("quilt", QUILT)
    growth, quilt, mesh = part(view, GrowthExplorer), part(view, QuiltExplorer), part(view, MeshViewer)
    boxes = [growth.bounds(), quilt.bounds(), mesh.bounds()]
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:  # disjoint along y (the rows), so no plane cuts through the mesh
            assert a[1, 1] < b[0, 1] or b[1, 1] < a[0, 1], (a, b)
    names = [e.name for i in (growth, quilt, mesh) for e in i.legend()]
    assert names == ["efros_leung plane", "sample plane", "quilting plane", "preview mesh"]
    assert {"texture_label", "sample_label"} <= set(growth.scene_nodes()) and "label" in quilt.scene_nodes()
    assert any(s.color == CUT_COLOR for s in quilt.legend()[0].swatches)
