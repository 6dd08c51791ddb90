"""End to end (issue 16, item 5): after the run, the large pictures the session's camera frustums carry take
a click as a pixel — in chromium, a click on camera 1's picture picks the pixel under the mouse in the
epipolar explorer (its inputs then hold that pixel), not only a click on the explorer's own image planes. The
scene legend lists the cameras and points drawn. Screenshot in ``test-output/``.

Where to click is worked out from the camera the page has (its first camera frames everything drawn, so the
pictures are wherever that puts them): pixels spread over camera 1's picture are projected through the
page's camera, and the one nearest the picture's centre that a click reaches is clicked — on the canvas (no
panel over it), on no other clickable picture (camera 2's, or an explorer plane: one nearer to the eye than
the frustum's picture would take the click, at the pixel of its own plane) and away from the 3D point's
gizmo. The explorer must then show that very pixel, within what one screen pixel spans of the picture.
"""

from __future__ import annotations

import math
from collections.abc import Callable
import re

import httpx
import numpy as np
import pytest
from conftest import ViewerPage
from test_browser import OUTPUT, TIMEOUT_MS, browser, lab_server  # noqa: F401  (fixtures)

SMALL = {"num_points": 120, "width": 320, "height": 240, "cx": 159.5, "cy": 119.5, "fx": 300.0, "fy": 300.0,
         "seed": 2}
FRUSTUM = "/lab/cameras/camera_000"
#: The other pictures that take clicks: camera 2's frustum, and the explorer's image planes.
OTHER_FRUSTUM = "/lab/cameras/camera_001"
PLANES = ("/explore/epipolar/rig/camera1/image", "/explore/epipolar/rig/camera2/image")
GIZMO = "/explore/epipolar/point/handle"
#: How far (CSS px) beyond the ends of the gizmo's arrows a click stays.
GIZMO_PX = 8.0


def picture_point(view: ViewerPage, frustum: str, width: int,
                  height: int) -> Callable[[np.ndarray], np.ndarray]:
    """``(u, v) -> (x, y, z)``: the point of ``frustum``'s picture (in its node's frame) that shows pixel
    ``(u, v)`` (edges at 0 and ``width``: :func:`lab.viewer.renderers.frustum_click_pixel`'s mapping) where
    viser draws it (:func:`lab.viewer.renderers.frustum_plane_depth`)."""
    fov, aspect, scale = (float(view.node_prop(frustum, key)) for key in ("fov", "aspect", "scale"))
    half = math.tan(fov / 2.0)
    depth = scale / (half * half * aspect / 3.0) ** (1.0 / 3.0)

    def point(uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        x = (uv[:, 0] / width - 0.5) * 2.0 * half * aspect * depth
        y = (uv[:, 1] / height - 0.5) * 2.0 * half * depth
        return np.column_stack([x, y, np.full(len(uv), depth)])

    return point


def quad(view: ViewerPage, name: str) -> np.ndarray | None:
    """The screen quad ``(4, 2)`` of a clickable picture: a frustum's (its corners) or an image node's."""
    kind = view.node_type(name)
    if kind is None:
        return None
    if "Frustum" in kind:
        width, height = SMALL["width"], SMALL["height"]
        corners = picture_point(view, name, width, height)(np.array([[0, 0], [width, 0], [width, height],
                                                                     [0, height]]))
    else:
        w, h = (float(view.node_prop(name, key)) / 2 for key in ("render_width", "render_height"))
        corners = np.array([[-w, -h, 0.0], [w, -h, 0.0], [w, h, 0.0], [-w, h, 0.0]])
    return view.screen_points(name, corners)


def inside(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Whether each point ``(N, 2)`` lies in the convex quad ``polygon`` (either winding)."""
    edges = np.roll(polygon, -1, axis=0) - polygon
    rel = points[:, None, :] - polygon[None, :, :]
    cross = edges[None, :, 0] * rel[:, :, 1] - edges[None, :, 1] * rel[:, :, 0]
    return np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)


def click_target(view: ViewerPage) -> tuple[np.ndarray, np.ndarray, float]:
    """``(pixel, screen point, tolerance)``: the pixel of camera 1's picture to click (see the module
    docstring), where it is on the page, and what one screen pixel spans of the picture there (image px)."""
    width, height = SMALL["width"], SMALL["height"]
    point = picture_point(view, FRUSTUM, width, height)
    us, vs = np.meshgrid(np.linspace(0.1, 0.9, 17) * width, np.linspace(0.1, 0.9, 13) * height)
    pixels = np.column_stack([us.ravel(), vs.ravel()])
    view.settle(FRUSTUM, point(pixels[:1]))
    screen = view.screen_points(FRUSTUM, point(pixels))
    free = view.on_canvas(screen)
    why = [f"{int(free.sum())} of {len(free)} on the canvas"]
    for other in (OTHER_FRUSTUM, *PLANES):
        covering = quad(view, other)
        if covering is not None:
            free &= ~inside(screen, covering)
            why.append(f"{int(free.sum())} off {other}")
    if view.node_type(GIZMO):  # its arrows, a scale long each way (and their cones), take the mouse
        reach = 1.25 * float(view.node_prop(GIZMO, "scale")) * np.vstack([np.eye(3), -np.eye(3)])
        arrows = view.screen_points(GIZMO, reach)
        lo, hi = arrows.min(axis=0) - GIZMO_PX, arrows.max(axis=0) + GIZMO_PX
        free &= ~np.all((screen >= lo) & (screen <= hi), axis=1)
        why.append(f"{int(free.sum())} off the gizmo's arrows {np.round([*lo, *hi])}")
    assert free.any(), (f"{'; '.join(why)}: no pixel of camera 1's picture can be clicked from the page's "
                        f"camera: picture at "
                        f"{np.round(quad(view, FRUSTUM))}, the others at "
                        f"{[np.round(q) for q in map(lambda n: quad(view, n), (OTHER_FRUSTUM, *PLANES))]}")
    centre = np.array([width / 2, height / 2])
    best = int(np.argmin(np.where(free, np.linalg.norm(pixels - centre, axis=1), np.inf)))
    pixel = pixels[best]
    step = view.screen_points(FRUSTUM, point(pixel + np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])))
    per_screen_px = 1.0 / max(min(np.linalg.norm(step[1] - step[0]), np.linalg.norm(step[2] - step[0])), 1e-6)
    return pixel, screen[best], max(1.0, 1.5 * per_screen_px)


@pytest.mark.e2e
def test_a_click_on_a_frustum_picture_picks_its_pixel(lab_server, browser):  # noqa: F811
    api_url, viewer_url = lab_server
    created = httpx.post(f"{api_url}/api/sessions", json={"module": "epipolar", "dataset": "correspondences",
                                                          "options": SMALL}, timeout=60)
    assert created.status_code == 201, created.text
    session_id = created.json()["id"]
    ran = httpx.post(f"{api_url}/api/sessions/{session_id}/run-until/refine_points", json={}, timeout=180)
    assert ran.status_code == 200, ran.text
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(f"{viewer_url}/?session={session_id}", timeout=TIMEOUT_MS)
    view = ViewerPage(page)
    page.get_by_text(re.compile(r"\(refine_points\): 2 cameras")).first.wait_for(timeout=TIMEOUT_MS)  # legend
    for name in (FRUSTUM, OTHER_FRUSTUM, *PLANES):
        view.eventually(lambda name=name: view.node_type(name), lambda kind: kind is not None)
    view.dismiss_software_rendering_notice()
    pixel, where, tolerance = click_target(view)
    page.mouse.click(float(where[0]), float(where[1]))
    picked = page.get_by_text(re.compile(r"image 1: yellow: picked pixel"))
    picked.first.wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(1000)
    page.screenshot(path=str(OUTPUT / "e2e-frustum-click.png"))
    explorer = view.folder("Epipolar explorer: click a pixel, drag a point")
    pixel_box = view.number_boxes(explorer, "pixel (u, v)")
    values = view.eventually(lambda: [float(pixel_box.nth(i).input_value()) for i in range(2)],
                             lambda got: np.allclose(got, pixel, atol=tolerance))
    np.testing.assert_allclose(values, pixel, atol=tolerance,
                               err_msg=f"clicked camera 1's picture at page {where.round(1)}")
