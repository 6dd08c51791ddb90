"""End to end (issue 16, item 5): after the run, the large pictures the session's camera frustums carry take
a click as a pixel — in chromium, a click on the centre of camera 1's picture picks its centre pixel in the
epipolar explorer (its inputs then hold the picked pixel), not only on the explorer's small image planes
(which show the same pixel along the same ray, should they be in front). The scene legend lists the cameras and points drawn. Screenshot in ``test-output/``.
"""

from __future__ import annotations

import math
import re

import httpx
import numpy as np
import pytest
from conftest import ViewerPage
from test_browser import OUTPUT, TIMEOUT_MS, browser, lab_server  # noqa: F401  (fixtures)

SMALL = {"num_points": 120, "width": 320, "height": 240, "cx": 159.5, "cy": 119.5, "fx": 300.0, "fy": 300.0,
         "seed": 2}


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
    frustum = "/lab/cameras/camera_000"  # in front of camera 2's, seen from the framed view
    page.get_by_text(re.compile(r"\(refine_points\): 2 cameras")).first.wait_for(timeout=TIMEOUT_MS)  # legend
    view.eventually(lambda: view.node_type(frustum), lambda kind: kind is not None)
    fov, aspect, scale = (float(view.node_prop(frustum, key)) for key in ("fov", "aspect", "scale"))
    half = math.tan(fov / 2.0)
    depth = scale / (half * half * aspect / 3.0) ** (1.0 / 3.0)  # where viser draws the picture
    view.click_node(frustum, (0.0, 0.0, depth))
    picked = page.get_by_text(re.compile(r"image 1: yellow: picked pixel"))
    picked.first.wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(1000)
    page.screenshot(path=str(OUTPUT / "e2e-frustum-click.png"))
    pixel_box = view.number_boxes(view.folder("Epipolar explorer: click a pixel, drag a point"), "pixel (u, v)")
    values = view.eventually(lambda: [float(pixel_box.nth(i).input_value()) for i in range(2)],
                             lambda got: np.allclose(got, (160.0, 120.0), atol=3.0))
    np.testing.assert_allclose(values, (160.0, 120.0), atol=3.0)  # the centre of the 320 x 240 image
