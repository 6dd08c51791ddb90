"""The saved 3D scene of a report: its page's initial camera sees everything it draws, and its poster is that
view drawn without a browser (issue 16: the page was blank for ~15 s in software rendering and the
undistorted image floated below the framed content, cut off)."""

from __future__ import annotations

import math

import numpy as np
from test_viewer_renderers import decode_embedded_scene

from lab.core import Cameras, Image, ImageSet, PointCloud
from lab.viewer.camera import CameraPose, aim, project
from lab.viewer.export import SCENE_VIEWPORT, export_scene
from lab.viewer.renderers import frustum_corners, scene_extent


def _scene_state() -> dict:
    """Two cameras around a cloud, the views they carry, and an image no camera carries (the pictures'
    row)."""
    views = ImageSet(tuple(Image(np.full((48, 64), grey, np.float32), f"v{i}")
                           for i, grey in enumerate((0.3, 0.6))))
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    angle = math.radians(20)
    R2 = np.array([[math.cos(angle), 0, -math.sin(angle)], [0, 1, 0], [math.sin(angle), 0, math.cos(angle)]])
    cameras = Cameras(np.stack([K, K]), np.stack([np.eye(3), R2]), np.array([[0, 0, 2.0], [0.5, 0, 2.0]]),
                      width=64, height=48, image="views")
    grid = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 6), np.linspace(-0.4, 0.4, 5), [0.0]), -1)
    grid = grid.reshape(-1, 3)
    undistorted = np.zeros((30, 40, 3), np.float32)
    undistorted[..., 0] = 1.0  # red: findable in the poster
    return {"views": views, "cameras": cameras, "board": PointCloud(grid), "undistorted": Image(undistorted)}


def _initial_camera(html: str) -> CameraPose:
    messages = {m["type"]: m for m in decode_embedded_scene(html) if m.get("initial")}
    assert math.isclose(messages["SetCameraFovMessage"]["fov"], SCENE_VIEWPORT.fov)
    return CameraPose(np.array(messages["SetCameraPositionMessage"]["position"]),
                      np.array(messages["SetCameraLookAtMessage"]["look_at"]),
                      np.array(messages["SetCameraUpDirectionMessage"]["position"]))


def _picture_corners(html: str) -> dict[str, np.ndarray]:
    """World corners ``(4, 3)`` of each laid-out picture of the page, from its messages (size and
    position)."""
    messages = decode_embedded_scene(html)
    sizes = {m["name"]: (m["props"]["render_width"], m["props"]["render_height"]) for m in messages
             if m.get("type") == "ImageMessage" and m["name"].startswith("/lab/pictures/")}
    where = {m["name"]: np.array(m["position"]) for m in messages if m.get("type") == "SetPositionMessage"}
    return {name: where[name] + np.array([[sx * w / 2, sy * h / 2, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
            for name, (w, h) in sizes.items()}


def test_the_saved_pages_initial_camera_sees_every_drawing_and_the_pictures_row():
    state = _scene_state()
    saved = export_scene(state)
    pose = _initial_camera(saved.html)
    assert np.allclose(pose.position, saved.pose.position) and np.allclose(pose.look_at, saved.pose.look_at)
    pictures = _picture_corners(saved.html)
    assert list(pictures) == ["/lab/pictures/undistorted"]
    content = np.concatenate([aim(state)[0], *pictures.values()])  # points, frustums' pictures, the row
    seen = project(content, pose, SCENE_VIEWPORT)
    assert np.all(np.isfinite(seen)) and seen.min() >= 0.0 and seen.max() <= 1.0, seen
    row = project(pictures["/lab/pictures/undistorted"], pose, SCENE_VIEWPORT)
    assert row[:, 1].max() - row[:, 1].min() > 0.05  # the picture is not a sliver at the edge


def test_the_poster_is_the_initial_cameras_view_drawn_without_a_browser():
    state = _scene_state()
    saved = export_scene(state)
    height, width = saved.poster.shape[:2]
    assert saved.poster.dtype == np.uint8
    assert math.isclose(width / height, SCENE_VIEWPORT.aspect, rel_tol=0.01)
    corners = _picture_corners(saved.html)["/lab/pictures/undistorted"]
    centre = project(corners.mean(axis=0, keepdims=True), saved.pose, SCENE_VIEWPORT)[0] * [width, height]
    r, g, b = saved.poster[int(centre[1]), int(centre[0])].astype(int)
    assert r > 200 and g < 60 and b < 60  # the red undistorted picture, where the page shows it
    glyphs = frustum_corners(state["cameras"], scene_extent(state.values())).reshape(-1, 4, 3)
    for view, grey in ((0, 0.3), (1, 0.6)):  # each frustum's picture: the grey of the view it carries
        middle = project(glyphs[view].mean(axis=0, keepdims=True), saved.pose, SCENE_VIEWPORT)[0]
        pixel = saved.poster[int(middle[1] * height), int(middle[0] * width)]
        assert np.allclose(pixel, 255 * grey, atol=12), (view, pixel)
    drawn = np.any(saved.poster != 255, axis=2)
    assert 0.02 < drawn.mean() < 0.9  # something, not everything


def test_an_empty_scene_has_a_blank_poster_and_no_camera():
    saved = export_scene({})
    assert saved.pose is None and np.all(saved.poster == 255)
