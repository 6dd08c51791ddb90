"""End to end: the epipolar module's interactions in headless chromium.

``?module=epipolar`` opens a session with the explorer's folders; a session run over REST up to the
pose opens at ``?session=ID`` with the four candidates' table (the chosen one marked) and the
inlier / outlier counts. Uses the lab server and browser fixtures of ``test_browser.py``;
screenshots go to ``test-output/``.
"""

from __future__ import annotations

import re

import httpx
import pytest
from test_browser import OUTPUT, TIMEOUT_MS, browser, lab_server  # noqa: F401  (fixtures)

EXPLORER = "Epipolar explorer: click a pixel, drag a point"
CANDIDATES = "The four pose candidates of E"
MATCHES = "Matches: inliers and outliers"
SMALL = {"num_points": 120, "width": 320, "height": 240, "cx": 159.5, "cy": 119.5, "fx": 300.0, "fy": 300.0,
         "seed": 2}


@pytest.mark.e2e
def test_epipolar_viewer_shows_the_interactions(lab_server, browser):  # noqa: F811
    api_url, viewer_url = lab_server
    page = browser.new_page(viewport={"width": 1400, "height": 900})

    # ?module=epipolar: a session of its own, with the three folders of the interactions
    page.goto(f"{viewer_url}/?module=epipolar", timeout=TIMEOUT_MS)
    page.wait_for_url(re.compile(r".*[?&]session=\w+"), timeout=TIMEOUT_MS)
    for title in (EXPLORER, CANDIDATES, MATCHES):
        page.get_by_text(title, exact=True).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(r"from the ground truth")).first.wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(2000)  # the image planes and rigs arrive
    page.screenshot(path=str(OUTPUT / "e2e-epipolar-explorer.png"))

    # a session run over REST up to the pose: the candidates' table and the match counts follow
    created = httpx.post(f"{api_url}/api/sessions", json={"module": "epipolar", "dataset": "correspondences",
                                                          "options": SMALL}, timeout=60)
    assert created.status_code == 201, created.text
    session_id = created.json()["id"]
    ran = httpx.post(f"{api_url}/api/sessions/{session_id}/run-until/recover_pose", json={}, timeout=120)
    assert ran.status_code == 200, ran.text
    page.goto(f"{viewer_url}/?session={session_id}", timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(r"passes \(chosen\)")).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(r"RANSAC kept \d+ of 120 matches")).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(r"is the pose recover_pose returned")).first.wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(2000)
    page.screenshot(path=str(OUTPUT / "e2e-epipolar-candidates.png"))
