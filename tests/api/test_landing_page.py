"""The landing page's lessons: cards open the viewer's lesson mode, summaries render their Markdown (HTML
escaped), modules are named for humans, and the page has an icon. The browser is Debian chromium."""

from __future__ import annotations

import pytest
from api_helpers import PIPELINES
from fastapi import APIRouter
from fastapi.testclient import TestClient
from test_api_landing_page import browser, serve  # noqa: F401  (the module's chromium fixture)

from lab.api import create_app
from lab.api.app import FAVICON_SVG
from lab.core import SessionStore
from lab.lessons.service import LessonService
from lab.lessons.store import SubmissionQueue

SUMMARY = ("Estimate the **fundamental matrix** with `normalize=True`; "
           "see [the notes](https://example.org/n) and [this](javascript:alert(1)). "
           "<img src=x onerror=\"window.hacked=1\"> <b>not bold</b>")
LESSONS = [{"id": "02-epipolar", "title": "Epipolar geometry", "summary": SUMMARY, "module": "epipolar",
            "module_title": "Epipolar geometry", "url": "/api/lessons/02-epipolar", "available": True,
            "tasks": [{"name": "f", "title": "The 8-point algorithm", "step": "f", "points": 10}]},
           {"id": "04-sfm", "title": "Structure from motion", "summary": "PnP `x`", "available": True,
            "module": "lab.modules.sfm_basics:PIPELINE",
            "module_title": "Structure from motion: the building blocks",
            "url": "/api/lessons/04-sfm", "tasks": []}]


def _lessons_router() -> APIRouter:
    router = APIRouter()

    @router.get("/api/lessons")
    def lessons():
        return LESSONS

    return router


def _app(viewer_url: str | None = "http://127.0.0.1:9999/"):
    return create_app(SessionStore(), modules=PIPELINES.__getitem__, module_names=list(PIPELINES),
                      viewer_url=viewer_url, extra_routers=[_lessons_router()])


@pytest.mark.e2e
def test_lesson_cards_open_the_viewer_and_render_their_summary_safely(browser):  # noqa: F811
    with serve(_app()) as url:
        page = browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(url + "/")
        page.wait_for_selector('[data-lesson="02-epipolar"] a.open-lesson')
        card = page.locator('[data-lesson="02-epipolar"]')
        assert card.locator("a.open-lesson").get_attribute("href") == "http://127.0.0.1:9999/?lesson=02-epipolar"
        assert card.locator("a.open-lesson").inner_text() == "Open the lesson"
        assert card.locator("a.lesson-json").get_attribute("href") == "/api/lessons/02-epipolar"
        summary = card.locator(".summary")
        assert summary.locator("strong").inner_text() == "fundamental matrix"
        assert summary.locator("code").inner_text() == "normalize=True"
        assert summary.locator("a").count() == 1  # the javascript: link is text, not a link
        assert summary.locator("a").get_attribute("href") == "https://example.org/n"
        assert summary.locator("img, b, script").count() == 0  # HTML in a summary is shown, not run
        text = summary.inner_text()
        assert "**" not in text and "`" not in text and "<img src=x" in text and "<b>not bold</b>" in text
        assert page.evaluate("window.hacked === undefined")
        sfm = page.locator('[data-lesson="04-sfm"]')
        assert "module: Structure from motion: the building blocks" in sfm.inner_text()
        assert "sfm_basics" not in sfm.inner_text()
        icon = page.locator('link[rel="icon"]')
        assert icon.count() == 1 and icon.get_attribute("href").startswith("data:image/svg+xml,")
        assert errors == []
        page.close()


@pytest.mark.e2e
def test_without_a_viewer_the_card_links_the_lessons_json(browser):  # noqa: F811
    with serve(_app(viewer_url=None)) as url:
        page = browser.new_page()
        page.goto(url + "/")
        page.wait_for_selector('[data-lesson="02-epipolar"] a.lesson-json')
        card = page.locator('[data-lesson="02-epipolar"]')
        assert card.locator("a.open-lesson").count() == 0
        assert card.locator("a.lesson-json").get_attribute("href") == "/api/lessons/02-epipolar"
        page.close()


def test_the_favicon_is_served():
    with TestClient(_app()) as client:
        response = client.get("/favicon.ico")
    assert response.status_code == 200 and response.headers["content-type"].startswith("image/svg+xml")
    assert response.text == FAVICON_SVG and response.text.startswith("<svg")


def test_the_lessons_list_names_modules_for_humans(tmp_path):
    app = create_app(SessionStore(), modules=PIPELINES.__getitem__, module_names=list(PIPELINES))
    app.state.lesson_service = LessonService(queue=SubmissionQueue(f"sqlite:///{tmp_path / 'db.sqlite'}"))
    try:
        listed = {entry["id"]: entry for entry in TestClient(app).get("/api/lessons").json()}
    finally:
        app.state.lesson_service.stop()
    sfm = listed["04-sfm"]
    assert sfm["module"] == "lab.modules.sfm_basics:PIPELINE"
    assert sfm["module_title"] == "Structure from motion: the building blocks"
    assert listed["01-calibration"]["module_title"] == "Camera calibration"
    assert "**" in listed["02-epipolar"]["summary"]  # Markdown in the JSON; the page renders it
