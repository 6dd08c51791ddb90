"""End to end (issue 17: "training follows the browser's camera in the viewer while it runs"): in chromium, a
NeRF session's training preview is rendered from the page's camera, and changes when the camera moves.

A session made over REST (rays and encoding done) is open in the page; train_nerf (the grid, a 60 s budget,
a preview every 10 iterations) runs over REST on the same session. The Images tab's ``preview`` panel
(its label says the picture's size) must take the canvas's shape instead of training view 0's square (the
preview follows the page's camera, whose canvas is not square), and show the object (not only the white
background: the camera's frame and the depths are right). Then the mouse wheel zooms the page's camera in,
as a student does: once the camera stands still again, the object must cover a clearly larger share of the
preview than before (the model alone, trained further from the same camera, does not grow the object).
A click on a pixel of a held-out picture shows that pixel's ray (its samples drawn, render_view run for it).
Screenshots in ``test-output/e2e-nerf-preview/``.
"""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import WAIT_MS, LabAPI, ViewerPage

pytestmark = pytest.mark.e2e

OUTPUT = Path(__file__).resolve().parents[2] / "test-output" / "e2e-nerf-preview"
TRAIN = {"method": "grid", "grid_resolution": 32, "batch_rays": 1024, "iterations": 100000,
         "budget_seconds": 60.0, "preview_every": 10}
LABEL = re.compile(r"^preview \((\d+)x(\d+)\)$")

#: The ``preview (WxH)`` panel's label and the bytes of its picture (fetched from the img's src).
_PREVIEW = """async () => {
  const labels = Array.from(document.querySelectorAll('*')).filter(
    (e) => e.children.length === 0 && /^preview \\(\\d+x\\d+\\)$/.test(e.textContent.trim()));
  for (const label of labels) {
    let box = label.parentElement;
    while (box && !box.querySelector('img')) box = box.parentElement;
    if (!box) continue;
    const img = box.querySelector('img');
    if (!img.src) continue;
    try {  // the picture may be replaced (its blob URL revoked) while it is read: read the next one then
      const bytes = new Uint8Array(await (await fetch(img.src)).arrayBuffer());
      return {label: label.textContent.trim(), data: Array.from(bytes)};
    } catch (error) {
      return null;
    }
  }
  return null;
}"""


def read_preview(view: ViewerPage) -> tuple[tuple[int, int], np.ndarray] | None:
    """((W, H) of the label, the RGB picture) of the preview panel, or None while there is none."""
    found = view.page.evaluate(_PREVIEW)
    if found is None:
        return None
    match = LABEL.match(found["label"])
    picture = cv2.imdecode(np.asarray(found["data"], dtype=np.uint8), cv2.IMREAD_COLOR)
    if match is None or picture is None:
        return None
    return (int(match.group(1)), int(match.group(2))), picture[:, :, ::-1] / 255.0


def footprint(picture: np.ndarray) -> float:
    """Share of the picture that is not the white background (the object)."""
    return float(np.mean(np.abs(picture - 1.0).max(axis=-1) > 0.15))


def settled_preview(view: ViewerPage, *, side: int = 64, timeout: float = 40.0) -> tuple[tuple[int, int],
                                                                                          np.ndarray]:
    """The preview once it is sharp (longest side ``side``: the camera stands still) and not square (it
    follows the page's canvas), two reads a second apart agreeing on its footprint within 0.02."""
    deadline = time.monotonic() + timeout
    last: tuple[tuple[int, int], np.ndarray] | None = None
    while time.monotonic() < deadline:
        now = read_preview(view)
        if now is not None and max(now[0]) == side and now[0][0] != now[0][1]:
            if last is not None and last[0] == now[0] and abs(footprint(last[1]) - footprint(now[1])) < 0.02:
                return now
            last = now
        time.sleep(1.0)
    assert last is not None, f"no sharp preview in the canvas's shape within {timeout:g} s: {read_preview(view)}"
    return last


def test_training_preview_follows_the_page_camera(served_lab, shared_browser):
    OUTPUT.mkdir(parents=True, exist_ok=True)
    api_url, viewer_url = served_lab
    lab_api = LabAPI(api_url)
    session = lab_api.create("nerf", "synthetic_object", {"train_views": 8, "test_views": 1})
    lab_api.run(session, "generate_rays", {})
    lab_api.run(session, "encode_positions", {})
    page = shared_browser.new_page(viewport={"width": 1400, "height": 900})
    try:
        page.goto(f"{viewer_url}/?session={session}", timeout=WAIT_MS)
        page.wait_for_function("() => window.__viserSceneTree !== undefined && window.__viserMutable !== "
                               "undefined", timeout=WAIT_MS)
        view = ViewerPage(page)
        view.eventually(lambda: view.scene_nodes("/lab/cameras"), bool)
        view.dismiss_software_rendering_notice()
        page.get_by_text("Follow my camera").first.wait_for(timeout=WAIT_MS)
        trained: dict = {}
        runner = threading.Thread(target=lambda: trained.update(lab_api.run(session, "train_nerf", TRAIN)))
        runner.start()
        try:
            (width, height), before = settled_preview(view)
            page.screenshot(path=str(OUTPUT / "before.png"))
            assert footprint(before) > 0.003, "the preview from the page's camera shows no object"
            canvas = page.evaluate("() => { const r = window.__viserMutable.canvas.getBoundingClientRect();"
                                   " return [r.left + r.width / 2, r.top + r.height / 2, r.width / r.height]; }")
            assert abs(width / height - canvas[2]) < 0.1, (width, height, canvas)
            page.mouse.move(canvas[0], canvas[1])
            for _ in range(6):  # zoom in, a notch at a time
                page.mouse.wheel(0, -240)
                time.sleep(0.15)
            time.sleep(1.0)
            size, after = settled_preview(view)
            page.screenshot(path=str(OUTPUT / "after.png"))
            cv2.imwrite(str(OUTPUT / "previews.png"),
                        (np.concatenate([before, cv2.resize(after, before.shape[1::-1])], axis=1)[:, :, ::-1]
                         * 255).astype(np.uint8))
            assert size == (width, height)
            assert footprint(after) > 1.3 * footprint(before), (footprint(before), footprint(after))
        finally:
            runner.join(timeout=120)
        assert trained.get("status") == "ok", trained
    finally:
        page.close()


HELD_OUT = "/lab/held_out_cameras/camera_000"
QUICK_GRID = {"method": "grid", "grid_resolution": 32, "batch_rays": 1024, "iterations": 150,
              "budget_seconds": 0.0, "preview_every": 150}


def test_a_click_on_a_held_out_picture_shows_its_ray(served_lab, shared_browser):
    """After render_held_out, a click on a pixel of held-out view 0's picture runs render_view for that
    pixel: the page then draws the ray's samples (``/lab/ray_samples``) and the session's render_view ran
    with the clicked pixel (within what one screen pixel spans of the picture)."""
    from test_e2e_frustum_click import picture_point

    OUTPUT.mkdir(parents=True, exist_ok=True)
    api_url, viewer_url = served_lab
    lab_api = LabAPI(api_url)
    session = lab_api.create("nerf", "synthetic_object", {"train_views": 4, "test_views": 1})
    for step, controls in (("generate_rays", {}), ("encode_positions", {}), ("train_nerf", QUICK_GRID),
                           ("render_held_out", {})):
        lab_api.run(session, step, controls)
    page = shared_browser.new_page(viewport={"width": 1400, "height": 900})
    try:
        page.goto(f"{viewer_url}/?session={session}", timeout=WAIT_MS)
        page.wait_for_function("() => window.__viserSceneTree !== undefined && window.__viserMutable !== "
                               "undefined", timeout=WAIT_MS)
        view = ViewerPage(page)
        view.eventually(lambda: view.node_type(HELD_OUT), lambda kind: kind is not None)
        view.dismiss_software_rendering_notice()
        page.get_by_text("Ray of a pixel").first.wait_for(timeout=WAIT_MS)
        point = picture_point(view, HELD_OUT, 100, 100)
        us, vs = np.meshgrid(np.linspace(20, 80, 13), np.linspace(20, 80, 13))
        pixels = np.column_stack([us.ravel(), vs.ravel()])
        view.settle(HELD_OUT, point(pixels[:1]))
        screen = view.screen_points(HELD_OUT, point(pixels))
        free = view.on_canvas(screen)
        assert free.any(), f"no pixel of held-out view 0's picture is on the free canvas: {screen.round()}"
        best = int(np.argmin(np.where(free, np.linalg.norm(pixels - 50.0, axis=1), np.inf)))
        page.mouse.click(float(screen[best][0]), float(screen[best][1]))
        view.eventually(lambda: view.node_type("/lab/ray_samples"), lambda kind: kind is not None)
        page.screenshot(path=str(OUTPUT / "ray-click.png"))
        assert view.node_type("/lab/ray_samples") is not None, "no ray samples drawn after the click"
        ran = [r for r in lab_api.history(session) if r["step"] == "render_view"]
        assert ran, "the click ran no render_view"
        step = view.screen_points(HELD_OUT, point(pixels[best] + np.array([[0.0, 0.0], [1.0, 0.0]])))
        tolerance = max(1.0, 1.5 / max(float(np.linalg.norm(step[1] - step[0])), 1e-6))
        clicked = np.array([ran[-1]["params"]["pixel_u"], ran[-1]["params"]["pixel_v"]], dtype=np.float64)
        np.testing.assert_allclose(clicked, pixels[best], atol=tolerance)
    finally:
        page.close()
