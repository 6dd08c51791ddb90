"""A lesson report in chromium: the 3D scene's place shows its poster at once, and the interactive scene loads
under it when asked and then replaces it (issue 16: the embedded scene was blank for ~15 s in software
rendering). Screenshots in the test's tmp dir."""

from __future__ import annotations

import pytest
from e2e.test_browser import CHROMIUM, CHROMIUM_ARGS

from lab.lessons.report import SCENE_REVEAL_MS, write_report

WAIT_MS = 90_000


@pytest.mark.e2e
def test_the_report_shows_the_scenes_poster_at_once_and_the_interactive_scene_when_asked(calibration_lesson,
                                                                                          tmp_path):
    from playwright.sync_api import sync_playwright

    index = write_report(calibration_lesson, tmp_path / "report", dataset="clean", seed=1)
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            page.goto(index.as_uri(), wait_until="load", timeout=WAIT_MS)
            box = page.locator("#scene")
            box.scroll_into_view_if_needed()
            poster = box.locator("img")
            assert poster.evaluate("img => img.complete && img.naturalWidth") > 0  # drawn with the page
            assert box.locator("iframe").count() == 0  # nothing heavy until asked
            width, height = box.evaluate("b => [b.clientWidth, b.clientHeight]")
            assert abs(width / height - 1.6) < 0.02  # the shape the scene's camera was fitted to
            box.screenshot(path=str(tmp_path / "report-poster.png"))

            page.get_by_role("button", name="Explore the 3D scene").click()
            assert "Loading the 3D scene" in page.locator("#scene-note").inner_text()
            frame = box.locator("iframe")
            assert frame.get_attribute("src") == "scene.html"
            assert poster.is_visible()  # the poster stays while the scene loads
            page.wait_for_function("() => document.getElementById('scene').classList.contains('loaded')",
                                   timeout=WAIT_MS + SCENE_REVEAL_MS)
            assert not poster.is_visible() and frame.is_visible()
            assert "Interactive 3D scene" in page.locator("#scene-note").inner_text()
            scene = frame.element_handle().content_frame()
            scene.wait_for_selector("canvas", timeout=WAIT_MS)
            box.screenshot(path=str(tmp_path / "report-scene.png"))
        finally:
            browser.close()
