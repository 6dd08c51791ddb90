"""A session's 3D scene as one self-contained HTML file, for headless lesson reports.

viser 1.1.1 serializes a *server's* scene (not a client's): ``ViserServer.scene.as_html()``
records every scene message (GUI messages are left out) into its ``.viser`` binary format,
compresses it and inlines it, base64-encoded, into viser's single-file web client
(``window.__VISER_EMBED_DATA__``), so the page plays the scene back with no server and no
network. :func:`export_scene_html` therefore starts a private viser server on a free
loopback port, draws the state with the viewer's renderers, frames the initial camera, takes the
HTML and stops the server.
"""

from __future__ import annotations

import contextlib
import io
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from lab.core.pipeline import Session
from lab.core.values import Cameras, Image, ImageSet
from lab.viewer.renderers import Canvas, StateDrawer, overlay_view, overlays_of, scene_bounds, viewpoint

#: How many views of an image set a report shows as pictures when no camera carries them.
MAX_VIEWS_AS_PICTURES = 8


def export_scene_html(session: Session | Mapping[str, Any], *, dark_mode: bool = False) -> str:
    """The 3D scene of ``session`` (or of a state dict) as a standalone HTML document.

    3D values (point clouds, camera frustums with their images and overlays, segments, meshes,
    splats) are drawn as in the viewer. Images that no camera carries (a stereo pair, a
    synthesized texture) are laid out as pictures in a row, with their 2D overlays, so every
    module's report shows something; plots are GUI elements, which viser does not serialize
    (reports use :func:`lab.viewer.renderers.curve_image` for them).
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
        _frame(server, state, pictures)
        return server.scene.as_html(dark_mode=dark_mode)
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()


def _pictures(scene: Any, state: Mapping[str, Any]) -> np.ndarray | None:
    """Images not carried by a camera: a row of pictures below the 3D content (or alone).

    Returns the ``(2, 3)`` bounds of the row (None when there is no picture)."""
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
        return None
    bounds = scene_bounds(state.values())
    if bounds is None:
        width, origin = 1.0, np.zeros(3)
    else:
        width = max(float(np.linalg.norm(bounds[1] - bounds[0])) / 3.0, 1e-3)
        origin = np.array([bounds[0, 0], bounds[1, 1] + width, bounds[0, 2]])  # below (y is down)
    x, tallest = 0.0, 0.0
    for name, rgb in pictures:
        height = width * rgb.shape[0] / rgb.shape[1]
        # viser's image plane has its rows along +y: in this y-down world the top row is at the top.
        scene.add_image(f"/lab/pictures/{name}", rgb, width, height, format="jpeg", jpeg_quality=90,
                        position=origin + np.array([x + width / 2, height / 2, 0.0]))
        x += width * 1.05
        tallest = max(tallest, height)
    return np.stack([origin, origin + np.array([x - 0.05 * width, tallest, 0.0])])


def _frame(server: Any, state: Mapping[str, Any], pictures: np.ndarray | None) -> None:
    """Initial camera of the saved page: as the viewer frames a session (:func:`viewpoint`)."""
    view = viewpoint(state.values())
    if view is None:  # only pictures: face their row (the camera looks along +z, y down)
        lo, hi = pictures if pictures is not None else np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
        center = (lo + hi) / 2
        view = (center - np.array([0.0, 0.0, 1.1 * max(hi[0] - lo[0], hi[1] - lo[1])]), center)
    position, look_at = view
    camera = server.initial_camera
    camera.up = (0.0, -1.0, 0.0)
    camera.position = tuple(float(v) for v in position)
    camera.look_at = tuple(float(v) for v in look_at)
    camera.fov = math.radians(60)


__all__ = ["export_scene_html"]
