"""End to end: the lab served by a subprocess, driven by headless Debian chromium through Playwright.

The landing page lists the modules and links the viewer; the viewer opens a session per tab, runs
a step when its Run button is clicked, and shows its metrics; the run is visible over REST; a
session made over REST opens at ``?session=ID`` and follows the steps a script runs; a lesson
opens at ``?lesson=ID`` with its text beside the pipeline, takes a student's file from the upload
button and compares its output with the reference's. Screenshots go to ``test-output/``
(gitignored). The server process group is always killed.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[2]
OUTPUT = ROOT / "test-output"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--enable-unsafe-swiftshader",
                 "--disable-gpu", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
TIMEOUT_MS = 60_000
RUN_TIMEOUT_MS = 180_000  # a run of several steps on shared, busy cores


# The module the tests drive, served by the CLI exactly as a user starts it.
MODULE, FIRST_STEP, SECOND_STEP, LONG_STEP, METRIC = (
    "calibration", "detect_corners", "estimate_homographies", "refine_calibration", "views_found")
LESSON = "01-calibration"
SOLUTION = ROOT / "tests" / "fixtures" / "submissions" / "calibration" / "solution.py"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def unfold(page: Any, label: Any, inside: str) -> Any:
    """The GUI folder whose title matches ``label`` (text or pattern), unfolded by a click on its title (again
    if the GUI was redrawn meanwhile) until ``inside`` (a locator in the folder) is visible; returns that
    locator (still hidden after five tries: the caller's wait or assertion reports it)."""
    title = page.get_by_text(label).first
    target = title.locator("xpath=..").locator(inside).first
    for _ in range(5):
        if target.is_visible():
            break
        title.click(timeout=TIMEOUT_MS)  # a page busy drawing (software WebGL, a loaded machine) is slow
        try:
            target.wait_for(state="visible", timeout=3000)
        except Exception:  # folded again or redrawn: try once more
            continue
    return target


def server_command(port: int, viewer_port: int) -> list[str]:
    return [sys.executable, "-m", "lab", "serve", "--host", "127.0.0.1", "--port", str(port),
            "--viewer-port", str(viewer_port)]


@pytest.fixture
def lab_server():
    """The lab in a subprocess (its own process group); yields (api_url, viewer_url)."""
    OUTPUT.mkdir(exist_ok=True)
    port, viewer_port = free_port(), free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with open(OUTPUT / "e2e-server.log", "w") as log:
        yield from _serve(port, viewer_port, env, log)


def _serve(port: int, viewer_port: int, env: dict[str, str], log: Any):
    process = subprocess.Popen(server_command(port, viewer_port), cwd=ROOT, env=env, stdout=log,
                               stderr=subprocess.STDOUT, start_new_session=True)
    api_url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90
        health = None
        while time.monotonic() < deadline:
            if process.poll() is not None:
                raise RuntimeError(f"the server exited with {process.returncode}; see "
                                   f"{OUTPUT / 'e2e-server.log'}")
            try:
                health = httpx.get(f"{api_url}/api/health", timeout=2).json()
                break
            except httpx.HTTPError:
                time.sleep(0.2)
        assert health is not None and health["status"] == "ok", "the lab did not answer /api/health"
        yield api_url, health["viewer_url"]
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=15)


@pytest.fixture
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


def step_title(api_url: str, step: str) -> str:
    module = httpx.get(f"{api_url}/api/modules/{MODULE}", timeout=30).json()
    return next(s["title"] for s in module["steps"] if s["name"] == step)


def step_number(api_url: str, step: str) -> int:
    module = httpx.get(f"{api_url}/api/modules/{MODULE}", timeout=30).json()
    return 1 + [s["name"] for s in module["steps"]].index(step)


@pytest.mark.e2e
def test_landing_page_viewer_and_a_step_run_from_the_gui(lab_server, browser):
    api_url, viewer_url = lab_server
    assert viewer_url.startswith("http://127.0.0.1:")
    page = browser.new_page(viewport={"width": 1400, "height": 900})

    # the landing page lists the modules and links the viewer
    page.goto(api_url + "/", timeout=TIMEOUT_MS)
    page.locator(f'[data-module="{MODULE}"]').wait_for(timeout=TIMEOUT_MS)
    link = page.locator("#viewer-link")
    link.wait_for(state="visible", timeout=TIMEOUT_MS)
    assert link.get_attribute("href").rstrip("/") == viewer_url.rstrip("/")
    page.screenshot(path=str(OUTPUT / "e2e-landing.png"), full_page=True)

    # the viewer opens a session of its own and puts its id in the address bar
    link.click()
    page.wait_for_url(re.compile(r".*[?&]session=\w+"), timeout=TIMEOUT_MS)
    session_id = re.search(r"session=(\w+)", page.url).group(1)
    first_title = step_title(api_url, FIRST_STEP)
    page.get_by_text(re.compile(rf"^1\. {re.escape(first_title)} . ready$")).wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(session_id).first.wait_for(timeout=TIMEOUT_MS)

    # run the first step with its Run button; its metrics appear, the status turns done
    page.get_by_role("button", name="Run", exact=True).first.click()
    page.get_by_text(re.compile(rf"^1\. {re.escape(first_title)} . done$")).wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(METRIC, exact=True).wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(1500)  # let the images arrive before the screenshot
    page.screenshot(path=str(OUTPUT / "e2e-viewer-after-run.png"))

    # the run is in the session's history over REST
    session = httpx.get(f"{api_url}/api/sessions/{session_id}", timeout=30).json()
    assert [(r["step"], r["status"]) for r in session["history"]] == [(FIRST_STEP, "ok")]
    assert METRIC in session["history"][0]["metrics"]

    # open the long step's folder and run everything up to it: progress, then done
    number, title = step_number(api_url, LONG_STEP), step_title(api_url, LONG_STEP)
    page.get_by_text(re.compile(rf"^{number}\. {re.escape(title)} . blocked$")).click()
    page.get_by_role("button", name="Run to here", exact=True).last.click()
    # six steps while the server may still compile its kernels (a fresh clone): a bound, not a timing
    page.get_by_text(re.compile(rf"^{number}\. {re.escape(title)} . done$")).wait_for(timeout=RUN_TIMEOUT_MS)
    page.get_by_text(re.compile(rf"^{LONG_STEP}: iteration .* ok$")).wait_for(timeout=TIMEOUT_MS)  # progress
    page.wait_for_timeout(2000)  # frustums, images and plots arrive
    page.screenshot(path=str(OUTPUT / "e2e-viewer-long-step.png"))
    session = httpx.get(f"{api_url}/api/sessions/{session_id}", timeout=30).json()
    assert session["history"][-1]["step"] == LONG_STEP and session["history"][-1]["status"] == "ok"
    assert session["steps"][LONG_STEP] == "done"


@pytest.mark.e2e
def test_a_session_made_over_rest_opens_and_follows_the_script(lab_server, browser):
    api_url, viewer_url = lab_server
    created = httpx.post(f"{api_url}/api/sessions", json={"module": MODULE}, timeout=60)
    assert created.status_code == 201, created.text
    session_id = created.json()["id"]
    ran = httpx.post(f"{api_url}/api/sessions/{session_id}/steps/{FIRST_STEP}", json={}, timeout=120)
    assert ran.status_code == 200, ran.text

    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(f"{viewer_url}/?session={session_id}", timeout=TIMEOUT_MS)
    first_title, second_title = step_title(api_url, FIRST_STEP), step_title(api_url, SECOND_STEP)
    page.get_by_text(re.compile(rf"^1\. {re.escape(first_title)} . done$")).wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(session_id).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_text(re.compile(rf"^2\. {re.escape(second_title)} . ready$")).wait_for(timeout=TIMEOUT_MS)

    # a script runs the next step: the open tab follows
    ran = httpx.post(f"{api_url}/api/sessions/{session_id}/steps/{SECOND_STEP}", json={}, timeout=120)
    assert ran.status_code == 200, ran.text
    page.get_by_text(re.compile(rf"^2\. {re.escape(second_title)} . done$")).wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(1000)
    page.screenshot(path=str(OUTPUT / "e2e-viewer-rest-session.png"))
    # the tab did not make a session of its own
    assert httpx.get(f"{api_url}/api/health", timeout=30).json()["sessions"] == 1


@pytest.mark.e2e
def test_lesson_mode_shows_the_text_and_compares_a_students_file(lab_server, browser):
    api_url, viewer_url = lab_server
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(f"{viewer_url}/?lesson={LESSON}", timeout=TIMEOUT_MS)

    # the lesson's text beside the pipeline; a session on its module; both in the address bar
    page.get_by_text("Task 1: the normalized DLT homography").first.wait_for(timeout=TIMEOUT_MS)
    page.wait_for_url(re.compile(r".*[?&]session=\w+"), timeout=TIMEOUT_MS)
    assert f"lesson={LESSON}" in page.url
    session_id = re.search(r"session=(\w+)", page.url).group(1)
    assert httpx.get(f"{api_url}/api/sessions/{session_id}", timeout=30).json()["module"] == MODULE
    first_title, second_title = step_title(api_url, FIRST_STEP), step_title(api_url, SECOND_STEP)
    page.get_by_text(re.compile(rf"^1\. {re.escape(first_title)} . ready$")).wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(1000)
    page.screenshot(path=str(OUTPUT / "e2e-lesson-text.png"))

    # the student's file through the upload button (the browser's file chooser)
    with page.expect_file_chooser(timeout=TIMEOUT_MS) as chooser:
        page.get_by_role("button", name="Upload my .py", exact=True).click()
    chooser.value.set_files(str(SOLUTION))
    page.get_by_text("Loaded solution.py:").wait_for(timeout=TIMEOUT_MS)

    # detect the corners, then compare the student's homographies with the reference's
    page.get_by_role("button", name="Run", exact=True).first.click()
    page.get_by_text(re.compile(rf"^1\. {re.escape(first_title)} . done$")).wait_for(timeout=TIMEOUT_MS)
    compare = unfold(page, re.compile(rf"^2\. {re.escape(second_title)} . ready$"),
                     "role=button[name='Compare with reference']")  # open its folder (again if redrawn)
    compare.click(timeout=TIMEOUT_MS)
    page.get_by_text("Your output matches the reference's.").wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(1000)
    page.screenshot(path=str(OUTPUT / "e2e-lesson-compare.png"))

    # Run with "use my code" on (it is, once the file defines the function): the student's step ran
    page.get_by_role("button", name="Run", exact=True).nth(1).click()
    page.get_by_text(re.compile(rf"^2\. {re.escape(second_title)} . done$")).wait_for(timeout=TIMEOUT_MS)
    history = httpx.get(f"{api_url}/api/sessions/{session_id}", timeout=30).json()["history"]
    assert [(r["step"], r["status"], r["replaced"]) for r in history] == [
        (FIRST_STEP, "ok", False), (SECOND_STEP, "ok", True)]
