"""The landing page in a real browser (Debian chromium through Playwright) against a live server on 127.0.0.1."""

from __future__ import annotations

import socket
import threading
from contextlib import contextmanager
from typing import Iterator

import pytest
import uvicorn
from api_helpers import PIPELINES, wait_until
from fastapi import APIRouter
from playwright.sync_api import sync_playwright
from toy_pipeline import TOY

from lab.api import create_app
from lab.core import SessionStore

pytestmark = pytest.mark.e2e

CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--disable-gpu", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@contextmanager
def serve(app) -> Iterator[str]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        wait_until(lambda: server.started, "the server to start")
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        sock.close()


@pytest.fixture(scope="module")
def browser():
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


def _lessons_router() -> APIRouter:
    router = APIRouter()

    @router.get("/api/lessons")
    def lessons():
        return [{"name": "zhang", "title": "Zhang's closed form", "summary": "Estimate K from homographies.",
                 "module": "toy", "tasks": ["estimate_homographies", "estimate_intrinsics"]}]

    return router


def test_landing_page_lists_modules_steps_datasets_and_links(browser, monkeypatch):
    monkeypatch.setattr("lab.api.app._lessons_router", lambda: None)  # this page has no lessons
    app = create_app(SessionStore(), modules=PIPELINES.__getitem__, module_names=list(PIPELINES),
                     viewer_url="http://127.0.0.1:9999/")
    with serve(app) as url:
        page = browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(url + "/")
        page.wait_for_selector('[data-module="toy"] [data-step="lift"]')
        assert page.title() == "Vision Lab"
        cards = page.locator("[data-module]")
        assert cards.count() == 2
        toy = page.locator('[data-module="toy"]')
        assert toy.locator("h3").inner_text() == "Toy"
        assert [s.get_attribute("data-step") for s in toy.locator("[data-step]").all()] == \
            ["add_noise", "mean_intensity", "lift"]
        assert "streams progress" in toy.locator('[data-step="lift"]').inner_text()
        assert "times scale." in toy.locator('[data-step="mean_intensity"]').inner_text()  # ``scale`` shown plain
        assert toy.locator(".chip").all_inner_texts() == ["gradients"]
        viewer = page.locator("#viewer-link")
        assert viewer.is_visible() and viewer.get_attribute("href") == "http://127.0.0.1:9999/"
        assert toy.locator("text=Open in the viewer").get_attribute("href") == "http://127.0.0.1:9999/?module=toy"
        assert page.locator('a[href="/docs"]').count() == 1
        assert page.locator("#lessons-section").is_hidden()  # no lessons router: no section
        assert page.locator(".example-module").first.inner_text() == "toy"
        assert errors == []
        page.close()


def test_landing_page_lists_lessons_and_unavailable_modules(browser):
    def loader(name):
        if name == "broken":
            raise ImportError("no module named lab.modules.broken")
        return TOY

    app = create_app(SessionStore(), modules=loader, module_names=["toy", "broken"], viewer_url=None,
                     extra_routers=[_lessons_router()])
    with serve(app) as url:
        page = browser.new_page()
        page.goto(url + "/")
        page.wait_for_selector('[data-lesson="zhang"]')
        lesson = page.locator('[data-lesson="zhang"]')
        assert lesson.locator("h3").inner_text() == "Zhang's closed form"
        assert "module: toy" in lesson.inner_text()
        assert page.locator("#viewer-link").is_hidden()  # no viewer running
        broken = page.locator('[data-module="broken"]')
        assert "Not available" in broken.inner_text() and "lab.modules.broken" in broken.inner_text()
        page.close()


def test_lesson_cards_open_the_lesson_in_the_viewer(browser, monkeypatch):
    app = create_app(SessionStore(), modules=PIPELINES.__getitem__, module_names=list(PIPELINES),
                     viewer_url="http://127.0.0.1:9999/", extra_routers=[_lessons_router()])
    with serve(app) as url:
        page = browser.new_page()
        page.goto(url + "/")
        page.wait_for_selector('[data-lesson="zhang"] a')
        link = page.locator('[data-lesson="zhang"]').locator("text=Open the lesson")
        assert link.get_attribute("href") == "http://127.0.0.1:9999/?lesson=zhang"
        page.close()


def test_api_docs_render_without_a_network(browser):
    """/docs is Swagger UI served from the package (no CDN): it renders our OpenAPI 3.1 operations
    in a browser whose every request outside this server is refused."""
    app = create_app(SessionStore(), modules=PIPELINES.__getitem__, module_names=list(PIPELINES))
    with serve(app) as url:
        page = browser.new_page()
        outside: list[str] = []

        def refuse_outside(route):
            if not route.request.url.startswith(url):
                outside.append(route.request.url)
                return route.abort()
            return route.continue_()

        page.route("**/*", refuse_outside)
        page.goto(url + "/docs")
        page.wait_for_selector(".opblock", timeout=20000)
        assert page.locator(".opblock").count() >= 5
        assert "Vision Lab" in page.locator(".title").first.inner_text()
        assert outside == []
        page.close()
