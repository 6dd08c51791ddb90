"""A session's 3D scene as one self-contained HTML file and a picture of it, for headless lesson reports.

viser 1.1.1 serializes a *server's* scene (not a client's): ``ViserServer.scene.as_html()``
records every scene message (GUI messages are left out) into its ``.viser`` binary format,
compresses it and inlines it, base64-encoded, into viser's single-file web client
(``window.__VISER_EMBED_DATA__``), so the page plays the scene back with no server and no
network. :func:`export_scene` therefore starts a private viser server on a free
loopback port, draws the state with the viewer's renderers, frames the initial camera, takes the
HTML and stops the server.

The page takes a while to show anything (about 15 s in software-rendered chromium, issue 16), so
:func:`export_scene` also draws a *poster*: the same scene seen by the same initial camera, projected
with OpenCV (pictures, frustums with their views, points, segments, mesh faces, back to front), which a
report shows at once in place of the page until the reader asks for the interactive one. The initial
camera fits everything the page draws into :data:`SCENE_VIEWPORT` (the report frames the page in that
shape): the 3D values, the frustums' pictures and the row of pictures no camera carries (an undistorted
image used to float below the framed content, cut off).
"""

from __future__ import annotations

import contextlib
import io
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from lab.core.pipeline import Session
from lab.core.values import Cameras, GaussianSplats, Image, ImageSet, Mesh, PointCloud, Segments3D
from lab.viewer.camera import CameraPose, Viewport, aim, fit_camera, project
from lab.viewer.renderers import (DEFAULT_CAMERA_COLOR, DEFAULT_MESH_COLOR, DEFAULT_POINT_COLOR, Canvas,
                                  StateDrawer, _color8, default_cloud_colors, frustum_corners, overlay_view,
                                  overlays_of, scene_extent)

#: How many views of an image set a report shows as pictures when no camera carries them.
MAX_VIEWS_AS_PICTURES = 8
#: The saved page's canvas (vertical field of view, width / height) its initial camera is fitted to.
SCENE_VIEWPORT = Viewport(fov=math.radians(60), aspect=16 / 10)
#: Width of the poster in pixels (its height follows :data:`SCENE_VIEWPORT`).
POSTER_WIDTH = 1280


@dataclass(frozen=True)
class ScenePicture:
    """A picture laid out in the scene: its pixels ``(H, W, 3)`` uint8 and its world corners ``(4, 3)``
    (top-left, top-right, bottom-right, bottom-left)."""

    rgb: np.ndarray
    corners: np.ndarray


@dataclass(frozen=True)
class SceneExport:
    """A saved scene: the standalone page, its poster ``(H, W, 3)`` uint8 RGB, and the initial camera both use
    (None when nothing is drawn)."""

    html: str
    poster: np.ndarray
    pose: CameraPose | None


def export_scene(session: Session | Mapping[str, Any], *, dark_mode: bool = False) -> SceneExport:
    """The 3D scene of ``session`` (or of a state dict) as a standalone HTML document and its poster.

    3D values (point clouds, camera frustums with their images and overlays, segments, meshes,
    splats) are drawn as in the viewer. Images that no camera carries (a stereo pair, a
    synthesized texture, an undistorted image) are laid out as pictures in a row, with their 2D
    overlays, so every module's report shows something; plots are GUI elements, which viser does not
    serialize (reports use :func:`lab.viewer.renderers.curve_image` for them).
    """
    import viser

    state = dict(session.state if isinstance(session, Session) else session)
    with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner with its URL
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        server.scene.set_up_direction("-y")
        drawer = StateDrawer(Canvas(scene=server.scene))
        drawer.sync(state)
        pictures = _pictures(server.scene, state)
        pose = scene_pose(state, pictures)
        if pose is not None:
            camera = server.initial_camera
            camera.up = _xyz(pose.up)
            camera.position = _xyz(pose.position)
            camera.look_at = _xyz(pose.look_at)
            camera.fov = SCENE_VIEWPORT.fov
        html = server.scene.as_html(dark_mode=dark_mode)
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
    return SceneExport(html, scene_poster(state, pictures, pose), pose)


def export_scene_html(session: Session | Mapping[str, Any], *, dark_mode: bool = False) -> str:
    """The standalone page of :func:`export_scene`."""
    return export_scene(session, dark_mode=dark_mode).html


def _xyz(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def _pictures(scene: Any, state: Mapping[str, Any]) -> list[ScenePicture]:
    """Images not carried by a camera: a row of pictures below the 3D content (or alone), added to
    ``scene``."""
    carried = {v.image for v in state.values() if isinstance(v, Cameras) and v.image}
    pictures: list[tuple[str, np.ndarray]] = []
    for name, value in sorted(state.items()):
        if name in carried:
            continue
        overlays = [o for _, o in overlays_of(state, name)]
        if isinstance(value, Image):
            pictures.append((name, overlay_view(value, overlays)))
        elif isinstance(value, ImageSet):
            for view in range(min(len(value), MAX_VIEWS_AS_PICTURES)):
                pictures.append((f"{name}/view_{view:03d}", overlay_view(value[view], overlays, view=view)))
    if not pictures:
        return []
    aimed = aim(state)
    if aimed is None:
        width, origin = 1.0, np.zeros(3)
    else:
        lo, hi = aimed[0].min(axis=0), aimed[0].max(axis=0)
        width = max(float(np.linalg.norm(hi - lo)) / 3.0, 1e-3)
        origin = np.array([lo[0], hi[1] + 0.1 * width, lo[2]])  # below (y is down) what is drawn
    placed, x = [], 0.0
    for name, rgb in pictures:
        height = width * rgb.shape[0] / rgb.shape[1]
        # viser's image plane has its rows along +y: in this y-down world the top row is at the top.
        scene.add_image(f"/lab/pictures/{name}", rgb, width, height, format="jpeg", jpeg_quality=90,
                        position=origin + np.array([x + width / 2, height / 2, 0.0]))
        corners = origin + np.array([[x, 0.0, 0.0], [x + width, 0.0, 0.0], [x + width, height, 0.0],
                                     [x, height, 0.0]])
        placed.append(ScenePicture(rgb, corners))
        x += width * 1.05
    return placed


def scene_pose(state: Mapping[str, Any], pictures: list[ScenePicture]) -> CameraPose | None:
    """The saved page's initial camera: the viewer's framing (:func:`lab.viewer.camera.aim`: the 3D values,
    the frustums' pictures) with the laid-out ``pictures`` too, fitted into :data:`SCENE_VIEWPORT`; facing
    the pictures when there is nothing else; None when nothing is drawn."""
    aimed = aim(state)
    corners = [p.corners for p in pictures]
    if aimed is None and not corners:
        return None
    points = np.concatenate([*(() if aimed is None else (aimed[0],)), *corners])
    forward = aimed[1] if aimed is not None else np.array([0.0, 0.0, 1.0])
    return fit_camera(points, forward, SCENE_VIEWPORT)


def scene_poster(state: Mapping[str, Any], pictures: list[ScenePicture], pose: CameraPose | None, *,
                 width: int = POSTER_WIDTH) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB: the saved scene as its initial camera ``pose`` sees it through
    :data:`SCENE_VIEWPORT`, drawn back to front with OpenCV: the laid-out ``pictures`` and each frustum's
    picture (perspective-warped), frustum edges, mesh faces (their vertex colours' mean), segments and
    points. A blank canvas when ``pose`` is None."""
    height = round(width / SCENE_VIEWPORT.aspect)
    canvas = np.full((height, width, 3), 255, np.uint8)
    if pose is None:
        return canvas
    size = np.array([width, height], dtype=np.float64)
    forward = pose.look_at - pose.position
    forward = forward / np.linalg.norm(forward)
    items: list[tuple[float, Callable[[np.ndarray], None]]] = []

    def pixels(points: np.ndarray) -> np.ndarray:
        return project(points, pose, SCENE_VIEWPORT) * size

    def depth(points: np.ndarray) -> float:
        return float(np.mean((np.asarray(points).reshape(-1, 3) - pose.position) @ forward))

    def add_picture(rgb: np.ndarray, corners: np.ndarray) -> None:
        quad = pixels(corners)
        if np.all(np.isfinite(quad)):
            items.append((depth(corners), partial(_warp_into, rgb=rgb, quad=quad)))

    def add_lines(starts: np.ndarray, ends: np.ndarray, color: tuple[int, int, int], thickness: int) -> None:
        a, b = pixels(starts), pixels(ends)
        for i in range(len(a)):
            if np.all(np.isfinite(a[i])) and np.all(np.isfinite(b[i])):
                line = partial(_line, p=_pixel(a[i]), q=_pixel(b[i]), color=color, thickness=thickness)
                items.append((depth(np.stack([starts[i], ends[i]])), line))

    extent = scene_extent(state.values())
    cloud_colors = default_cloud_colors(state)
    for picture in pictures:
        add_picture(picture.rgb, picture.corners)
    for name, value in state.items():
        if isinstance(value, Cameras):
            _add_cameras(state, value, extent, add_picture, add_lines)
        elif isinstance(value, PointCloud | GaussianSplats):
            xyz = value.xyz if isinstance(value, PointCloud) else value.centers
            own = value.colors if isinstance(value, PointCloud) else value.rgbs
            default = cloud_colors.get(name, DEFAULT_POINT_COLOR)
            at = pixels(xyz)
            for i in map(int, np.flatnonzero(np.all(np.isfinite(at), axis=1))):
                items.append((depth(xyz[i]), partial(_dot, p=_pixel(at[i]), color=_color8(own, i, default))))
        elif isinstance(value, Segments3D):
            for i in range(len(value.start)):
                add_lines(value.start[i:i + 1], value.end[i:i + 1],
                          _color8(value.colors, i, DEFAULT_POINT_COLOR), 1)
        elif isinstance(value, Mesh):
            _add_mesh(value, pixels, depth, items)
    for _, draw in sorted(items, key=lambda item: -item[0]):  # far first
        draw(canvas)
    return canvas


def _add_cameras(state: Mapping[str, Any], cameras: Cameras, extent: float,
                 add_picture: Callable[[np.ndarray, np.ndarray], None],
                 add_lines: Callable[[np.ndarray, np.ndarray, tuple[int, int, int], int], None]) -> None:
    """A poster's frustums: each one's picture (the view it carries, with its overlays) and its edges."""
    images = state.get(cameras.image) if cameras.image else None
    if isinstance(images, Image):
        images = ImageSet((images,))
    overlays = [o for _, o in overlays_of(state, cameras.image)] if isinstance(images, ImageSet) else []
    views = cameras.views if cameras.views is not None else np.arange(len(cameras))
    corners = frustum_corners(cameras, extent).reshape(-1, 4, 3)  # TL, BL, TR, BR
    for i in range(len(cameras)):
        tl, bl, tr, br = corners[i]
        view = int(views[i])
        if isinstance(images, ImageSet) and 0 <= view < len(images):
            add_picture(overlay_view(images[view], overlays, view=view), np.stack([tl, tr, br, bl]))
        center = cameras.centers[i]
        rim = np.stack([tl, tr, br, bl])
        color = _color8(cameras.colors, i, DEFAULT_CAMERA_COLOR)
        add_lines(np.repeat(center[None], 4, axis=0), rim, color, 2)
        add_lines(rim, np.roll(rim, -1, axis=0), color, 2)


def _add_mesh(mesh: Mesh, pixels: Callable[[np.ndarray], np.ndarray], depth: Callable[[np.ndarray], float],
              items: list[tuple[float, Callable[[np.ndarray], None]]]) -> None:
    """A poster's mesh: each face filled with its vertices' mean colour (or the plain mesh colour)."""
    at = pixels(mesh.vertices)
    for face in np.asarray(mesh.faces):
        quad = at[face]
        if not np.all(np.isfinite(quad)):
            continue
        if mesh.vertex_colors is not None:
            mean = (np.clip(mesh.vertex_colors[face].mean(axis=0), 0.0, 1.0) * 255.0 + 0.5).astype(int)
            color = (int(mean[0]), int(mean[1]), int(mean[2]))
        else:
            color = DEFAULT_MESH_COLOR
        items.append((depth(mesh.vertices[face]),
                      partial(_polygon, polygon=np.round(quad).astype(np.int32), color=color)))


def _pixel(at: np.ndarray) -> tuple[int, int]:
    return int(at[0]), int(at[1])


def _line(out: np.ndarray, *, p: tuple[int, int], q: tuple[int, int], color: tuple[int, int, int],
          thickness: int) -> None:
    cv2 = _cv2()
    cv2.line(out, p, q, color, thickness, cv2.LINE_AA)


def _dot(out: np.ndarray, *, p: tuple[int, int], color: tuple[int, int, int]) -> None:
    _cv2().circle(out, p, 3, color, -1)


def _polygon(out: np.ndarray, *, polygon: np.ndarray, color: tuple[int, int, int]) -> None:
    cv2 = _cv2()
    cv2.fillConvexPoly(out, polygon, color, cv2.LINE_AA)


def _warp_into(out: np.ndarray, *, rgb: np.ndarray, quad: np.ndarray) -> None:
    """Paint ``rgb`` ``(h, w, 3)`` into ``out`` where its corners (top-left, top-right, bottom-right,
    bottom-left) land at ``quad`` ``(4, 2)`` pixels."""
    cv2 = _cv2()
    h, w = rgb.shape[:2]
    source = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float32)
    matrix = cv2.getPerspectiveTransform(source, quad.astype(np.float32))
    size = (out.shape[1], out.shape[0])
    warped = cv2.warpPerspective(np.ascontiguousarray(rgb), matrix, size, flags=cv2.INTER_AREA)
    mask = cv2.warpPerspective(np.full((h, w), 255, np.uint8), matrix, size, flags=cv2.INTER_NEAREST) > 0
    out[mask] = warped[mask]


def _cv2() -> Any:
    import cv2

    return cv2


__all__ = ["MAX_VIEWS_AS_PICTURES", "POSTER_WIDTH", "SCENE_VIEWPORT", "SceneExport", "ScenePicture",
           "export_scene", "export_scene_html", "scene_pose", "scene_poster"]
