"""Renderers: every value type drawn into a real viser server (127.0.0.1, a free port), 2D overlays
and charts checked pixel by pixel, and the HTML export decoded back into scene messages."""

from __future__ import annotations

import base64
import math
import re

import msgspec
import numpy as np
import pytest
import viser
import zstandard

from lab.core import (Cameras, Curve, GaussianSplats, Image, ImageSet, Mesh, PointCloud, Points2D, Segments2D,
                      Segments3D)
from lab.viewer import export_scene_html
from lab.viewer.renderers import (POINT_COLORS, SEGMENT_COLORS, WORST_BAR_COLOR, Canvas,
                                  StateDrawer, curve_image,
                                  overlay_view, overlays_of, scene_extent, to_rgb8)


@pytest.fixture
def scene_drawer(server):
    return StateDrawer(Canvas(scene=server.scene))


@pytest.fixture
def gui_drawer(server):
    return StateDrawer(Canvas(scene=server.scene, gui=server.gui))


def node(server, name):
    return server.scene.get_handle_by_name(f"/lab/{name}")


def black(height=20, width=30):
    return Image(np.zeros((height, width), np.float32), "black")


def is_color(pixel, color, tol=40):
    return bool(np.all(np.abs(pixel.astype(int) - np.array(color)) <= tol))


# --- pure 2D helpers -----------------------------------------------------------------------------
def test_to_rgb8_gray_and_color():
    gray = to_rgb8(np.array([[0.0, 1.0], [0.5, 2.0]], np.float32))
    assert gray.shape == (2, 2, 3) and gray.dtype == np.uint8
    assert gray[0, 1].tolist() == [255, 255, 255] and gray[1, 1].tolist() == [255, 255, 255]  # clipped
    assert gray[1, 0].tolist() == [128, 128, 128]
    rgb = to_rgb8(np.dstack([np.ones((2, 2)), np.zeros((2, 2)), np.zeros((2, 2))]))
    assert rgb[0, 0].tolist() == [255, 0, 0]


def test_overlay_points_are_open_circles_in_their_colour():
    points = Points2D(np.array([[10.0, 5.0]]), colors=np.array([[1.0, 0.0, 0.0]]), image="black")
    rgb = overlay_view(black(), [points], max_side=None)
    assert rgb.shape == (20, 30, 3)
    assert rgb[5, 10].tolist() == [0, 0, 0]  # the centre stays visible
    ring = rgb[3:8, 8:13].reshape(-1, 3)
    assert (ring[:, 0] > 100).any() and (ring[:, 1] < 30).all()  # a red ring around it
    assert rgb[15:, :].max() == 0  # nothing drawn far away


def test_overlay_segments_default_red_and_filtered_by_view():
    segments = Segments2D(np.array([[2.0, 2.0], [20.0, 2.0]]), np.array([[2.0, 15.0], [20.0, 15.0]]),
                          view=np.array([0, 1]), image="black")
    view0 = overlay_view(black(), [segments], view=0, max_side=None)
    assert is_color(view0[10, 2], SEGMENT_COLORS[0])  # the vertical line x = 2 on view 0
    assert view0[10, 20].max() == 0  # the segment of view 1 is not drawn on view 0
    view1 = overlay_view(black(), [segments], view=1, max_side=None)
    assert is_color(view1[10, 20], SEGMENT_COLORS[0]) and view1[10, 2].max() == 0


def test_overlay_points_default_colour_and_views():
    points = Points2D(np.array([[5.0, 5.0], [20.0, 10.0]]), view=np.array([0, 1]), image="black")
    rgb = overlay_view(black(), [points], view=1, max_side=None)
    assert rgb[:, :14].max() == 0
    drawn = rgb[rgb.max(axis=2) > 0]
    assert len(drawn) and np.all(np.argmax(drawn, axis=1) == np.argmax(POINT_COLORS[0]))


def test_overlay_shrinks_and_enlarges_keeping_positions():
    big = Image(np.zeros((800, 1000), np.float32))
    points = Points2D(np.array([[500.0, 400.0]]), colors=np.array([[0.0, 1.0, 0.0]]))
    small = overlay_view(big, [points], max_side=500)
    assert small.shape == (400, 500, 3)
    ys, xs = np.nonzero(small[:, :, 1])
    assert abs(xs.mean() - 249.75) < 1.5 and abs(ys.mean() - 199.75) < 1.5  # centre follows the scaling
    tiny = overlay_view(Image(np.ones((4, 6), np.float32)), max_side=640, min_side=60)
    assert tiny.shape == (40, 60, 3) and tiny.min() == 255  # nearest neighbour, integer factor


def test_overlays_of_picks_points_and_segments_of_one_image():
    state = {"a": Points2D(np.zeros((1, 2)), image="images"), "b": Points2D(np.zeros((1, 2)), image="other"),
             "c": Segments2D(np.zeros((1, 2)), np.ones((1, 2)), image="images"), "d": np.zeros(3)}
    assert [name for name, _ in overlays_of(state, "images")] == ["a", "c"]


def test_bar_chart_worst_bar_is_red():
    curve = Curve(np.arange(3.0), np.array([1.0, 5.0, 2.0]), kind="bar", categories=("v0", "v1", "v2"),
                  title="per-view RMS")
    rgb = curve_image(curve, width=300, height=200)
    assert rgb.shape == (200, 300, 3)
    red = np.all(np.abs(rgb.astype(int) - WORST_BAR_COLOR) <= 10, axis=2)
    columns = np.nonzero(red.sum(axis=0) > 20)[0]  # the filled bar, not the caption text
    left, plot_w = 52, 300 - 52 - 10
    assert len(columns) and left + plot_w / 3 <= columns.min() and columns.max() < left + 2 * plot_w / 3
    blue = np.all(np.abs(rgb.astype(int) - (90, 140, 210)) <= 10, axis=2)
    assert blue[:, : left + int(plot_w / 3)].sum() > 0 and blue[:, left + int(2 * plot_w / 3):].sum() > 0
    # the worst bar is the tallest one
    assert red.sum(axis=0).max() > blue.sum(axis=0).max()


def test_line_chart_draws_each_series():
    curve = Curve(np.arange(10.0), np.stack([np.linspace(1, 0, 10), np.linspace(0, 1, 10)]), kind="line")
    rgb = curve_image(curve)
    blue = np.all(np.abs(rgb.astype(int) - (31, 119, 180)) <= 30, axis=2)
    orange = np.all(np.abs(rgb.astype(int) - (255, 127, 14)) <= 30, axis=2)
    assert blue.sum() > 50 and orange.sum() > 50
    # series 0 goes down: its leftmost pixels are higher (smaller row) than its rightmost ones
    ys, xs = np.nonzero(blue)
    assert ys[xs < xs.min() + 10].mean() < ys[xs > xs.max() - 10].mean()


def test_viewpoint_looks_over_the_cameras_shoulders():
    from lab.viewer.renderers import viewpoint

    assert viewpoint([np.zeros(3)]) is None  # nothing 3D
    # two cameras at z = -1 looking along +z at a board at z = 0
    cameras = Cameras(np.stack([np.eye(3)] * 2), np.stack([np.eye(3)] * 2),
                      np.array([[0.5, 0, 1.0], [-0.5, 0, 1.0]]),
                      width=4, height=3)
    board = Mesh(np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0], [0, 0.5, 0]]), np.array([[0, 1, 2]]))
    eye, look_at = viewpoint([cameras, board])
    assert eye[2] < -1.0 and eye[1] < 0  # behind the cameras, and above them (world up is -y)
    np.testing.assert_allclose(look_at, [0.0, 0.0, -0.5])  # the centre of cameras and board


def test_scene_extent_is_stable_and_defaults_to_one():
    assert scene_extent([]) == 1.0
    cloud = PointCloud(np.array([[0.0, 0, 0], [3.0, 4.0, 0]]))
    assert scene_extent([cloud]) == pytest.approx(2 ** (round(2 * math.log2(5.0)) / 2))


# --- 3D renderers --------------------------------------------------------------------------------
def test_point_cloud(server, scene_drawer):
    xyz = np.random.default_rng(0).normal(size=(50, 3))
    colors = np.tile([[1.0, 0.0, 0.0]], (50, 1))
    assert scene_drawer.sync({"cloud": PointCloud(xyz, colors)}) == ["cloud"]
    handle = node(server, "cloud")
    assert isinstance(handle, viser.PointCloudHandle)
    np.testing.assert_allclose(handle.points, xyz, atol=1e-6)
    assert handle.colors.shape == (50, 3) and (handle.colors[:, 0] == 255).all()


def test_cameras_frustums_carry_their_view_with_overlays(server, scene_drawer):
    images = ImageSet(tuple(Image(np.full((48, 64), 0.5, np.float32), f"view {i}") for i in range(3)))
    K = np.stack([np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])] * 2)
    R = np.stack([np.eye(3)] * 2)
    t = np.array([[0.0, 0, 2.0], [1.0, 0, 2.0]])
    cameras = Cameras(K, R, t, width=64, height=48, image="images", views=np.array([2, 0]),
                      colors=np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    corners = Points2D(np.array([[32.0, 24.0]]), view=np.array([2]), colors=np.array([[0.0, 0.0, 1.0]]))
    scene_drawer.sync({"images": images, "cameras": cameras, "corners": corners})
    first = server.scene.get_handle_by_name("/lab/cameras/camera_000")
    second = server.scene.get_handle_by_name("/lab/cameras/camera_001")
    assert isinstance(first, viser.CameraFrustumHandle)
    np.testing.assert_allclose(first.position, [0, 0, -2])  # C = -R^T t
    np.testing.assert_allclose(second.position, [-1, 0, -2])
    assert first.fov == pytest.approx(2 * math.atan(24 / 50))
    assert first.aspect == pytest.approx(64 / 48)
    assert tuple(first.color) == (255, 0, 0) and tuple(second.color) == (0, 255, 0)
    # camera 0 carries view 2, where the corner is: its picture has the blue circle, camera 1's not
    assert first.image.shape == (48, 64, 3)
    assert (first.image[:, :, 2].astype(int) - first.image[:, :, 0] > 100).any()
    assert not (second.image[:, :, 2].astype(int) - second.image[:, :, 0] > 100).any()


def test_camera_orientation_is_camera_to_world(server, scene_drawer):
    angle = 0.3
    R = np.array([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    cameras = Cameras(np.eye(3) * [100, 100, 1], R, np.array([0.0, 0, 1]), width=200, height=100)
    scene_drawer.sync({"cameras": cameras})
    handle = server.scene.get_handle_by_name("/lab/cameras/camera_000")
    rotation = viser.transforms.SO3(np.asarray(handle.wxyz)).as_matrix()
    np.testing.assert_allclose(rotation, R.T, atol=1e-9)
    assert handle.image is None  # no image set named


def test_segments3d_mesh_and_splats(server, scene_drawer):
    segments = Segments3D(np.zeros((2, 3)), np.eye(3)[:2], colors=np.array([[0.0, 0, 1], [1, 0, 0]]))
    mesh = Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
    coloured = Mesh(mesh.vertices, mesh.faces, vertex_colors=np.eye(3))
    splats = GaussianSplats(np.zeros((2, 3)), np.stack([np.eye(3) * 0.01] * 2), np.full((2, 3), 0.5),
                            np.full(2, 0.9))
    scene_drawer.sync({"lines": segments, "board": mesh, "painted": coloured, "splats": splats})
    lines = node(server, "lines")
    assert isinstance(lines, viser.LineSegmentsHandle)
    assert lines.points.shape == (2, 2, 3) and tuple(lines.colors[0, 0]) == (0, 0, 255)
    assert isinstance(node(server, "board"), viser.MeshHandle)
    np.testing.assert_allclose(node(server, "board").vertices, mesh.vertices)
    assert isinstance(node(server, "painted"), viser.GlbHandle)  # vertex colours travel as a GLB
    assert isinstance(node(server, "splats"), viser.GaussianSplatHandle)


def test_values_that_are_gone_are_removed_and_unchanged_ones_kept(server, scene_drawer):
    cloud = PointCloud(np.zeros((3, 3)))
    other = PointCloud(np.ones((3, 3)))
    assert scene_drawer.sync({"cloud": cloud, "other": other}) == ["cloud", "other"]
    first = node(server, "cloud")
    assert scene_drawer.sync({"cloud": cloud, "other": other}) == []  # nothing changed: nothing redrawn
    assert node(server, "cloud") is first
    scene_drawer.sync({"cloud": PointCloud(np.full((3, 3), 2.0))})  # re-run upstream: new value, other gone
    assert node(server, "other") is None
    assert node(server, "cloud") is not first
    scene_drawer.sync({})
    assert node(server, "cloud") is None and scene_drawer.drawn == {}


def test_plain_arrays_and_overlays_are_not_drawn_alone(server, scene_drawer):
    state = {"K": np.eye(3), "corners": Points2D(np.zeros((2, 2))), "images": ImageSet((black(),))}
    assert scene_drawer.sync(state) == []  # no GUI on this canvas: the image set is GUI-only


def test_a_failing_renderer_is_reported_and_the_rest_drawn(server, scene_drawer, monkeypatch):
    from lab.viewer import renderers

    def broken(*args, **kwargs):
        raise ValueError("boom")

    monkeypatch.setattr(renderers.RENDERERS[Segments3D], "draw", broken)
    drawn = scene_drawer.sync({"cloud": PointCloud(np.zeros((1, 3))),
                               "lines": Segments3D(np.zeros((1, 3)), np.ones((1, 3)))})
    assert drawn == ["cloud"]
    assert "boom" in scene_drawer.errors["lines"]


# --- GUI renderers ------------------------------------------------------------------------------
def test_image_set_panel_has_a_view_slider_and_overlays(server, gui_drawer):
    images = ImageSet(tuple(Image(np.zeros((20, 30), np.float32), f"v{i}") for i in range(4)))
    corners = Points2D(np.array([[10.0, 10.0], [20.0, 10.0]]), view=np.array([0, 3]))
    gui_drawer.sync({"images": images, "corners": corners})
    drawn = gui_drawer.drawn["images"]
    assert isinstance(drawn.handles[0], viser.GuiFolderHandle)
    slider, picture = drawn.parts["slider"], drawn.parts["image"]
    assert isinstance(slider, viser.GuiSliderHandle) and (slider.min, slider.max, slider.step) == (0, 3, 1)
    assert isinstance(picture, viser.GuiImageHandle)
    assert "images[0] v0" in picture.label and "corners: 1" in picture.label
    gui_drawer.show_view("images", 3)  # e.g. a frustum was clicked
    assert slider.value == 3 and "images[3] v3" in picture.label
    assert gui_drawer.sync({"images": images}) == ["images"]  # corners gone: redrawn without them, in place
    assert gui_drawer.drawn["images"] is drawn and drawn.parts["image"] is picture
    assert "corners" not in picture.label and "images[3] v3" in picture.label
    assert gui_drawer.canvas.views["images"] == 3  # the view shown survives a redraw
    fewer = ImageSet(images.images[:2])  # a new set with fewer views: the slider shrinks, the view is clamped
    gui_drawer.sync({"images": fewer})
    assert (slider.max, slider.value, slider.visible) == (1, 1, True) and "images[1] v1" in picture.label
    gui_drawer.sync({"images": ImageSet(images.images[:1])})  # one view: no slider
    assert not slider.visible and picture.visible and "images[0] v0" in picture.label
    gui_drawer.sync({"images": ImageSet(())})  # none: no picture, the folder says so
    assert not picture.visible and "empty" in drawn.handles[0].label


def test_image_set_view_switch_redraws_the_picture(server, gui_drawer, monkeypatch):
    images = ImageSet((black(), Image(np.ones((20, 30), np.float32), "white")))
    shown = []
    original = viser.GuiImageHandle.image.fset

    def record(self, value):
        shown.append(np.asarray(value).copy())
        original(self, value)

    monkeypatch.setattr(viser.GuiImageHandle, "image", viser.GuiImageHandle.image.setter(record))
    gui_drawer.sync({"images": images})
    assert shown[-1].max() == 0  # view 0 (black) first
    gui_drawer.show_view("images", 1)
    assert shown[-1].min() == 255  # the white view
    assert gui_drawer.canvas.views["images"] == 1


def test_curves_are_uplot_lines_and_bar_images(server, gui_drawer):
    loss = Curve(np.arange(5.0), np.array([1.0, 0.5, 0.25, 0.1, 0.05]), kind="line", title="loss")
    rms = Curve(np.arange(3.0), np.array([0.2, 0.4, 0.1]), kind="bar", categories=("a", "b", "c"))
    gui_drawer.sync({"cost": loss, "per_view_rms": rms})
    line = gui_drawer.drawn["cost"].handles[0]
    bars = gui_drawer.drawn["per_view_rms"].handles[0]
    assert isinstance(line, viser.GuiUplotHandle)
    assert len(line.data) == 2 and np.allclose(line.data[1], loss.y[0])
    assert line.title == "loss"
    assert isinstance(bars, viser.GuiImageHandle) and bars.label == "per_view_rms"


def test_single_image_panel(server, gui_drawer):
    gui_drawer.sync({"undistorted": Image(np.zeros((10, 10, 3), np.float32))})
    handle = gui_drawer.drawn["undistorted"].handles[0]
    assert isinstance(handle, viser.GuiImageHandle) and "10x10" in handle.label


# --- export ---------------------------------------------------------------------------------------
def decode_embedded_scene(html: str) -> list[dict]:
    """The scene messages inside an exported page (viser's .viser format: zstd(msgpack + buffers))."""
    data = re.search(r'window.__VISER_EMBED_DATA__="([^"]+)"', html).group(1)
    raw = base64.b64decode(data)
    inner = zstandard.ZstdDecompressor().decompress(raw[8:],
                                                    max_output_size=int.from_bytes(raw[:8], "little"))
    length = int.from_bytes(inner[:8], "little")
    payload = msgspec.msgpack.decode(inner[8:8 + length])
    return [message for _, message in payload["messages"]]


def test_export_scene_html_is_a_standalone_page_with_the_scene():
    images = ImageSet((Image(np.full((48, 64), 0.5, np.float32), "v0"),))
    state = {"images": images,
             "cameras": Cameras(np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), np.eye(3),
                                np.array([0, 0, 2.0]),
                                width=64, height=48, image="images"),
             "cloud": PointCloud(np.zeros((4, 3))),
             "per_view_rms": Curve(np.arange(1.0), np.array([0.3]), kind="bar")}
    html = export_scene_html(state)
    assert html.lstrip().lower().startswith("<!doctype html>") and "</html>" in html
    types = [m.get("type") for m in decode_embedded_scene(html)]
    assert "CameraFrustumMessage" in types and "PointCloudMessage" in types
    assert not any(str(t).startswith("Gui") for t in types)  # plots are GUI: not serialized


def test_export_lays_out_images_that_no_camera_carries():
    html = export_scene_html({"left": Image(np.zeros((8, 8), np.float32)),
                              "pair": ImageSet((black(), black()))})
    names = [m.get("name") for m in decode_embedded_scene(html) if m.get("type") == "ImageMessage"]
    assert sorted(names) == ["/lab/pictures/left", "/lab/pictures/pair/view_000",
                             "/lab/pictures/pair/view_001"]
