"""The scene legend (lab/viewer/legend.py): every 3D value type says how it is drawn and what its colours
mean, without module code; the viewer shows it beside a "Fit view" button."""

from __future__ import annotations

import numpy as np

from lab.core.values import Cameras, GaussianSplats, Image, Mesh, PointCloud, Segments3D
from lab.viewer.legend import colour_groups, legend_entries, legend_entry, legend_html
from lab.viewer.renderers import DEFAULT_CAMERA_COLOR, DEFAULT_POINT_COLOR


def cameras(count: int, colors=None) -> Cameras:
    K = np.tile(np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), (count, 1, 1))
    R = np.tile(np.eye(3), (count, 1, 1))
    t = np.column_stack([np.arange(count, dtype=float), np.zeros(count), np.zeros(count)])
    return Cameras(K=K, R=R, t=t, width=640, height=480, colors=colors, image="images")


def test_uncoloured_values_get_their_default_colour_and_a_count():
    entry = legend_entry("cloud", PointCloud(np.zeros((5, 3))))
    assert entry.kind == "points" and entry.count == 5
    assert [(s.color, s.marks) for s in entry.swatches] == [(DEFAULT_POINT_COLOR, "all 5 points")]
    rig = legend_entry("rig", cameras(3))
    assert rig.swatches[0].color == DEFAULT_CAMERA_COLOR and "click one" in rig.note


def test_a_few_colours_are_listed_with_what_they_mark_many_are_their_own():
    tints = np.array([[1.0, 0, 0], [0, 1.0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    entry = legend_entry("rig", cameras(4, tints))
    marks = {s.color: s.marks for s in entry.swatches}
    assert marks == {(255, 0, 0): "camera 0, 2", (0, 255, 0): "camera 1, 3"}
    swatches, note = colour_groups(np.random.default_rng(0).random((50, 3)), 50, (0, 0, 0), noun="point",
                                   plural="points")
    assert swatches == () and "each of the points in its own colour" in note


def test_only_3d_values_are_in_the_legend_and_its_html_escapes_names():
    state = {"image": Image(np.zeros((4, 4))), "b<script>": PointCloud(np.zeros((2, 3))),
             "lines": Segments3D(np.zeros((3, 3)), np.ones((3, 3))),
             "board": Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]])),
             "splats": GaussianSplats(np.zeros((1, 3)), np.eye(3)[None], np.zeros((1, 3)), np.ones(1))}
    entries = legend_entries(state)
    assert [e.name for e in entries] == ["b<script>", "board", "lines", "splats"]
    page = legend_html(entries, {"lines": "triangulate"})
    assert "<script>" not in page and "b&lt;script&gt;" in page and "(triangulate)" in page
    assert "background:#3c3c3c" in page  # the default point grey, as a square
    assert "Nothing drawn in 3D yet" in legend_html([])


def test_the_viewer_shows_the_legend_after_a_run_and_fit_view_frames_the_scene(server, store):
    from lab.viewer.app import ClientView, ModuleCatalog
    from lab.modules import get_pipeline

    view = ClientView(server, store, ModuleCatalog({"epipolar": get_pipeline("epipolar")}), is_client=False,
                      background=False)
    view.start({})
    # before any step: what the interactions draw from the truth (the rig, the candidates), with their titles
    before = view.scene_panel.legend.content
    assert "<b>explorer cameras</b>" in before and "(Epipolar explorer" in before
    assert "<b>cameras</b>" not in before  # no state value drawn yet
    assert view.how_to.label == "How to use this"
    view.run_all()
    content = view.scene_panel.legend.content
    drawn = [e.name for e in legend_entries(dict(view.session.state))]
    assert drawn and all(f"<b>{name}</b>" in content for name in drawn)
    assert "cameras" in content and "points" in content and "<b>pose candidates</b>" in content
    view.fit_view()  # a server-side view has no client camera: it must not fail


def test_clouds_without_colours_get_distinct_colours_the_legend_names():
    from lab.viewer.renderers import CLOUD_COLORS, RENDERERS, Canvas, default_cloud_colors

    state = {"samples": PointCloud(np.ones((4, 3))), "noised": PointCloud(np.zeros((3, 3))),
             "coloured": PointCloud(np.zeros((2, 3)), np.ones((2, 3)))}
    colours = default_cloud_colors(state)
    assert colours == {"noised": CLOUD_COLORS[0], "samples": CLOUD_COLORS[1]}
    assert len(set(CLOUD_COLORS)) == len(CLOUD_COLORS)
    entries = {e.name: e for e in legend_entries(state)}
    assert entries["samples"].swatches[0].color == CLOUD_COLORS[1]
    assert entries["noised"].swatches[0].color == CLOUD_COLORS[0]

    class Scene:  # records what the renderer asks viser for
        def add_point_cloud(self, name, **kwargs):
            self.colors = kwargs["colors"]
            return object()

    scene = Scene()
    RENDERERS[PointCloud].draw(Canvas(scene=scene), "samples", state["samples"], state, 0.0)
    assert tuple(scene.colors) == CLOUD_COLORS[1]  # drawn in the colour the legend lists


def test_the_scene_panel_lists_what_interactions_draw_with_their_title(server):
    from lab.viewer.legend import LegendEntry, ScenePanel, Swatch

    class Draws:
        title = "Sampler steps"

        def legend(self):
            return [LegendEntry("x_t", "points", 7, (Swatch((90, 140, 255), "the samples at the frame"),))]

    class Broken:
        title = "broken"

        def legend(self):
            raise RuntimeError("a bug")

    panel = ScenePanel(server.gui, on_fit=lambda: None)
    content = panel.show({"cloud": PointCloud(np.zeros((2, 3)))}, {"cloud": "dataset"}, [Draws(), Broken()])
    assert "<b>cloud</b>" in content and "(dataset)" in content
    assert "<b>x_t</b>" in content and "(Sampler steps)" in content and "background:#5a8cff" in content
    assert "the samples at the frame" in content and panel.legend.content == content
