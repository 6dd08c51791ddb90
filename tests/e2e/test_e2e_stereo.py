"""End to end: the stereo module's interactions in headless chromium.

``?module=stereo`` opens a session with the three folders of the interactions; a small synthetic session run
over REST to winner-take-all opens at ``?session=ID`` with the cost curves of the image's centre pixel (its
true disparity and the session's choice), the bad-pixel summary of the maps and the depth-uncertainty
text. Uses the lab server and browser fixtures of ``test_browser.py``; screenshots go to ``test-output/``.
"""

from __future__ import annotations

import re

import httpx
import pytest
from test_browser import OUTPUT, TIMEOUT_MS, browser, lab_server  # noqa: F401  (fixtures)

MAPS = "Disparity and error maps"
COSTS = "Matching costs of a pixel"
BASELINE = "Baseline and depth resolution"
SMALL = {"width": 112, "height": 84, "baseline": 0.3}


@pytest.mark.e2e
def test_stereo_viewer_shows_the_interactions(lab_server, browser):  # noqa: F811
    api_url, viewer_url = lab_server
    page = browser.new_page(viewport={"width": 1400, "height": 900})

    page.goto(f"{viewer_url}/?module=stereo", timeout=TIMEOUT_MS)
    page.wait_for_url(re.compile(r".*[?&]session=\w+"), timeout=TIMEOUT_MS)
    for title in (MAPS, COSTS, BASELINE):
        page.get_by_text(title, exact=True).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(r"Run rectify_pair")).first.wait_for(timeout=TIMEOUT_MS)
    page.screenshot(path=str(OUTPUT / "e2e-stereo-open.png"))

    created = httpx.post(f"{api_url}/api/sessions", json={"module": "stereo", "dataset": "synthetic",
                                                          "options": SMALL}, timeout=120)
    assert created.status_code == 201, created.text
    session_id = created.json()["id"]
    ran = httpx.post(f"{api_url}/api/sessions/{session_id}/run-until/winner_take_all",
                     json={"cost_volume": {"max_disparity": 24}}, timeout=180)
    assert ran.status_code == 200, ran.text
    page.goto(f"{viewer_url}/?session={session_id}", timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(r"Pixel \(56, 42\): true disparity")).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(r"the session's winner-take-all")).first.wait_for(timeout=TIMEOUT_MS)
    against = re.compile(r"winner-take-all\W+disparity against the truth")
    page.get_by_text(against).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(r"Baseline B = 0.3 m")).first.wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(2000)  # the image plane and the plots arrive
    page.screenshot(path=str(OUTPUT / "e2e-stereo-maps.png"))
    page.get_by_role("tab", name="Plots").click()  # the cost curves and the depth uncertainty (uPlot)
    page.get_by_text(re.compile(r"matching costs at \(56, 42\)")).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(r"depth uncertainty u_z")).first.wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(1000)
    page.screenshot(path=str(OUTPUT / "e2e-stereo-costs.png"))
