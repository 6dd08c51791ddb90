"""End to end: the texture module's interactions in headless chromium, driven as a student drives them.

A small procedural session grows a 12 x 12 Efros–Leung texture (over REST) and opens at ``?session=ID``.
In the page: the growth replay slider is typed to 20 pixels and the texture plane in the scene then
shows exactly the first 20 pixels of the fill order (the rest dark); a pixel typed into the (row, col)
inputs is explained (fill rank and copied window from the trace, its window outlined on the plane at
the right place); a mouse click on the texture plane in the canvas explains the pixel under it.
Quilting run over REST while the tab is open: the block slider picks a block whose position and
source match the layout, outlined on the quilt; the mesh folder's dropdowns wrap the quilt on a
cylinder. Uses the lab server and browser fixtures of ``test_browser.py`` and ``lab_api`` /
``viewer_page`` of ``conftest.py``; screenshots go to ``test-output/``.
"""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from test_browser import OUTPUT, TIMEOUT_MS, browser, lab_server  # noqa: F401  (fixtures)

GROWTH = "Efros–Leung: growth and matches"
QUILTING = "Quilting: overlaps and cuts"
MESH = "Texture on a mesh"
SMALL = {"pattern": "blobs", "size": 20, "target_size": 24}
SIDE = 12  # the Efros–Leung output is SIDE x SIDE
EL = {"size": [SIDE, SIDE], "window": 5}
QUILT = {"size": [30, 30], "block": 10, "overlap": 3}
UNKNOWN = (70, 70, 90)  # the colour of not-yet-grown pixels in the replay
TEXTURE_NODE = "/explore/texture/efros_leung/texture"


def plane_x(col: float, width: int, scale: float, left: float = 0.0) -> float:
    """Scene x of column ``col`` (pixel centres at integers) on a plane of ``width`` pixels centred at
    ``left``."""
    return left + (col - (width - 1) / 2) * scale


@pytest.mark.e2e
def test_texture_growth_replay_pixel_inspection_quilt_blocks_and_mesh(
        lab_server, lab_api, viewer_page):  # noqa: F811
    viewer_url = lab_server[1]
    session_id = lab_api.create("texture", "procedural", SMALL)
    lab_api.run(session_id, "synthesize_efros_leung", EL)
    trace = lab_api.value(session_id, "efros_leung_trace")
    fill_order, source = np.array(trace["fill_order"]), np.array(trace["source"])
    png = lab_api.value(session_id, "efros_leung", "png")
    texture = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]

    view = viewer_page(f"{viewer_url}/?session={session_id}")
    page = view.page
    growth = view.folder(GROWTH)
    grown = re.compile(rf"^{SIDE} x {SIDE} grown in \d+ onion layers")
    growth.get_by_text(grown).wait_for(timeout=TIMEOUT_MS)
    assert view.slider_value(growth, "grown pixels") == (SIDE * SIDE, SIDE * SIDE)

    # replay the growth: after 20 pixels the plane shows exactly those, in the fill order, the rest dark
    view.type_numbers(growth, "grown pixels", 20)
    grown = fill_order < 20
    frame = view.eventually(lambda: view.node_image(TEXTURE_NODE),
                            lambda image: image is not None
                            and (image == UNKNOWN).all(axis=2).sum() == SIDE**2 - 20)
    assert frame.shape == (SIDE, SIDE, 3)
    assert np.array_equal((frame == UNKNOWN).all(axis=2), ~grown)
    assert np.array_equal(frame[grown], texture[grown])
    assert view.slider_value(growth, "grown pixels")[0] == 20

    # type a pixel and explain it: its fill rank and the window it copied come from the trace
    row, col = 3, 7
    view.type_numbers(growth, "pixel (row, col)", row, col)
    growth.get_by_role("button", name="Explain this pixel").click()
    top, left = source[row, col] - EL["window"] // 2
    growth.get_by_text(re.compile(rf"^Pixel \({row}, {col}\) was filled {fill_order[row, col] + 1}th.*"
                                  rf"window at \({top}, {left}\) of the sample")).wait_for(timeout=TIMEOUT_MS)
    nodes = view.eventually(lambda: view.scene_nodes("/explore/texture/efros_leung/"), lambda n: len(n) >= 5)
    assert {f"/explore/texture/efros_leung/{n}" for n in ("texture", "sample", "window",
                                                          "candidates", "chosen")} \
        <= set(nodes)
    # the window's outline on the texture plane: 5 x 5 pixels around (row, col), pixel edges at +-0.5; the
    # growth row holds the texture and then the sample, one scale for both, the larger PLANE_SIDE across
    from lab.viewer.interactions.texture import GROWTH_ROW_Y, PLANE_SIDE

    sample_png = lab_api.value(session_id, "sample", "png")
    sample_h, sample_w = cv2.imdecode(np.frombuffer(sample_png, np.uint8), cv2.IMREAD_COLOR).shape[:2]
    scale = PLANE_SIDE / max(SIDE, sample_w, sample_h)
    row_width = SIDE * scale + 0.15 * PLANE_SIDE + sample_w * scale
    centre_x = -row_width / 2 + SIDE * scale / 2
    outline = view.node_points("/explore/texture/efros_leung/window")
    np.testing.assert_allclose([outline[:, 0].min(), outline[:, 0].max()],
                               [plane_x(col - 2.5, SIDE, scale, centre_x),
                                plane_x(col + 2.5, SIDE, scale, centre_x)], atol=1e-5)
    np.testing.assert_allclose([outline[:, 1].min(), outline[:, 1].max()],
                               [plane_x(row - 2.5, SIDE, scale, GROWTH_ROW_Y),
                                plane_x(row + 2.5, SIDE, scale, GROWTH_ROW_Y)], atol=1e-5)
    for label in ("window when filled", "candidates in the sample"):  # the panels in the Images tab
        page.get_by_text(label, exact=True).wait_for(timeout=TIMEOUT_MS)
    page.screenshot(path=str(OUTPUT / "e2e-texture-pixel.png"))

    # click the texture plane in the canvas, on pixel (5, 2): that pixel is explained, the inputs follow
    view.click_node(TEXTURE_NODE, (plane_x(2, SIDE, scale), plane_x(5, SIDE, scale), 0.0))
    explained = re.compile(rf"^Pixel \(5, 2\) was filled {fill_order[5, 2] + 1}th")
    growth.get_by_text(explained).wait_for(timeout=TIMEOUT_MS)
    assert [box.input_value() for box in view.number_boxes(growth, "pixel (row, col)").all()] == ["5", "2"]

    # quilt over REST while the tab is open: the quilting folder follows; pick block 3 with its slider
    lab_api.run(session_id, "quilt", QUILT)
    layout = lab_api.value(session_id, "quilting_layout")
    positions, sources = layout["positions"], layout["sources"]
    quilting = view.folder(QUILTING)
    first = re.compile(rf"^Block 1 at \({positions[1][0]}, {positions[1][1]}\) of the quilt")
    quilting.get_by_text(first).wait_for(timeout=TIMEOUT_MS)
    assert view.slider_value(quilting, "block") == (1, len(positions) - 1)
    view.type_numbers(quilting, "block", 3)
    (y, x), (sy, sx) = positions[3], sources[3]
    third = re.compile(rf"^Block 3 at \({y}, {x}\) of the quilt, copied from \({sy}, {sx}\) of the "
                       r"sample\. .*along the cut")
    quilting.get_by_text(third).wait_for(timeout=TIMEOUT_MS)
    quilt_scale = 2.0 / 30
    box = view.eventually(lambda: view.node_points("/explore/texture/quilting/block"),
                          lambda p: p is not None
                          and abs(p[:, 0].min() - plane_x(x - 0.5, 30, quilt_scale)) < 1e-4)
    np.testing.assert_allclose([box[:, 0].min(), box[:, 0].max()],
                               [plane_x(x - 0.5, 30, quilt_scale),
                                plane_x(x + QUILT["block"] - 0.5, 30, quilt_scale)],
                               atol=1e-4)

    # the texture on a mesh: Efros–Leung's (the first made) until the student picks the quilt, then its shape
    mesh = view.folder(MESH)
    mesh.get_by_text(f"efros_leung ({SIDE} x {SIDE}) on a torus, repeated 2x.",
                     exact=True).wait_for(timeout=TIMEOUT_MS)
    view.choose(mesh, "texture", "quilting")
    mesh.get_by_text("quilting (30 x 30) on a torus, repeated 2x.", exact=True).wait_for(timeout=TIMEOUT_MS)
    view.choose(mesh, "shape", "cylinder")
    mesh.get_by_text("quilting (30 x 30) on a cylinder, repeated 2x.",
                     exact=True).wait_for(timeout=TIMEOUT_MS)
    assert view.node_type("/explore/texture/mesh/surface") == "GlbMessage"
    page.wait_for_timeout(1000)  # the mesh arrives before the screenshot
    page.screenshot(path=str(OUTPUT / "e2e-texture-quilt-mesh.png"))
