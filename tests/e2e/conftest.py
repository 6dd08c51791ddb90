"""Helpers shared by the e2e tests of module interactions: read what a viewer page shows and drive its GUI.

The lab server and the browser are the fixtures of ``test_browser.py`` (one per test);
``served_lab`` and ``shared_browser`` are the same, one per test module (the server's log must then
hold no traceback); ``unfold`` (in ``test_browser.py``) opens a GUI folder by its title as a user does.
Here: :class:`ViewerPage` (fixture ``viewer_page``) wraps a Playwright page open on the viewer. It finds an interaction's
GUI folder by its title, types into the number box beside a labelled slider or vector, picks a
dropdown option, and reads the 3D scene as the page holds it through viser's end-to-end test hook
``window.__viserSceneTree`` (each node's message: type and props) and ``window.__viserMutable``
(the three.js camera and node objects, to click a point of a node in the canvas). :class:`LabAPI`
(fixture ``lab_api``) is the REST side a script uses: make a session, run steps, read values.
"""

from __future__ import annotations

import os
import time
from typing import Any
from collections.abc import Callable

import cv2
import httpx
import numpy as np
import pytest
from test_browser import CHROMIUM, CHROMIUM_ARGS, OUTPUT, _serve, free_port

#: How long a page element or scene node may take to appear (ms). Generous: the machine is shared.
WAIT_MS = 60_000

_NODE_PROPS = """([name, key]) => {
  const node = window.__viserSceneTree.getState()[name];
  if (!node) return null;
  const value = node.message.props[key];
  if (value === undefined || value === null) return null;
  if (ArrayBuffer.isView(value)) return {kind: value.constructor.name, data: Array.from(value)};
  return {kind: typeof value, data: value};
}"""

_PROJECT = """([name, point]) => {
  const mutable = window.__viserMutable;
  const object = mutable.nodeRefFromName[name];
  if (!object) return null;
  object.updateWorldMatrix(true, false);
  const world = object.localToWorld(object.position.clone().set(point[0], point[1], point[2]));
  const ndc = world.clone().project(mutable.camera);
  const rect = mutable.canvas.getBoundingClientRect();
  return [rect.left + (ndc.x + 1) / 2 * rect.width, rect.top + (1 - ndc.y) / 2 * rect.height];
}"""

_PROJECT_MANY = """([name, points]) => {
  const mutable = window.__viserMutable;
  const object = mutable.nodeRefFromName[name];
  if (!object) return null;
  object.updateWorldMatrix(true, false);
  mutable.camera.updateMatrixWorld();
  const rect = mutable.canvas.getBoundingClientRect();
  return points.map((point) => {
    const world = object.localToWorld(object.position.clone().set(point[0], point[1], point[2]));
    const ndc = world.clone().project(mutable.camera);
    return [rect.left + (ndc.x + 1) / 2 * rect.width, rect.top + (1 - ndc.y) / 2 * rect.height];
  });
}"""

_ON_CANVAS = """(points) => {
  const canvas = window.__viserMutable.canvas;
  return points.map(([x, y]) => document.elementFromPoint(x, y) === canvas);
}"""


class ViewerPage:
    """A viewer tab in Playwright: GUI folders and inputs by label, and the scene nodes it received."""

    def __init__(self, page: Any) -> None:
        self.page = page

    @staticmethod
    def eventually(read: Callable[[], Any], check: Callable[[Any], bool], *,
                   timeout: float = WAIT_MS / 1000) -> Any:
        """Poll ``read()`` until ``check`` accepts it and return that value; on timeout, return the last one
        read (the caller's assertion then shows what the page held)."""
        deadline = time.monotonic() + timeout
        value = read()
        while not check(value) and time.monotonic() < deadline:
            time.sleep(0.2)
            value = read()
        return value

    # --- GUI ---------------------------------------------------------------------------------------
    def folder(self, title: str) -> Any:
        """The GUI folder titled ``title`` (its frame: the title and everything inside), once shown."""
        folder = self.page.get_by_text(title, exact=True).first.locator("xpath=..")
        folder.wait_for(timeout=WAIT_MS)
        return folder

    @staticmethod
    def number_boxes(scope: Any, label: str) -> Any:
        """The typed-number boxes of the input labelled ``label`` in ``scope`` (a slider has one, a vector
        two)."""
        return scope.locator(f"xpath=.//label[normalize-space()='{label}']"
                             "/ancestor::div[.//input[@type='text']][1]//input[@type='text']")

    def type_numbers(self, scope: Any, label: str, *values: float) -> None:
        """Type ``values`` into the boxes of input ``label``, as a student does, each followed by Enter."""
        boxes = self.number_boxes(scope, label)
        assert boxes.count() == len(values), f"{label!r} has {boxes.count()} number boxes, not {len(values)}"
        for box, value in zip(boxes.all(), values, strict=True):
            box.fill(f"{value:g}")
            box.press("Enter")

    @staticmethod
    def slider_value(scope: Any, label: str) -> tuple[float, float]:
        """(value, max) of the slider labelled ``label`` in ``scope``, as the page shows them."""
        thumb = scope.locator(f"xpath=.//label[normalize-space()='{label}']"
                              "/ancestor::div[.//*[@role='slider']][1]//*[@role='slider']").first
        return float(thumb.get_attribute("aria-valuenow")), float(thumb.get_attribute("aria-valuemax"))

    def choose(self, scope: Any, label: str, option: str) -> None:
        """Pick ``option`` in the dropdown labelled ``label`` in ``scope``."""
        field = f"xpath=.//label[normalize-space()='{label}']/ancestor::div[.//input][1]//input"
        scope.locator(field).first.click()
        self.page.get_by_role("option", name=option, exact=True).click()

    # --- scene -------------------------------------------------------------------------------------
    def scene_nodes(self, prefix: str = "/") -> list[str]:
        """Names of the scene nodes the page holds now, under ``prefix``."""
        names = self.page.evaluate(
            "() => window.__viserSceneTree ? Object.keys(window.__viserSceneTree.getState()) : []")
        return sorted(name for name in names if name.startswith(prefix))

    def node_type(self, name: str) -> str | None:
        return self.page.evaluate("(name) => { const n = window.__viserSceneTree.getState()[name]; return n "
                                  "? n.message.type : null; }", name)

    def node_prop(self, name: str, key: str) -> Any:
        """Prop ``key`` of node ``name`` as the page holds it (typed arrays as numpy arrays); None when
        absent."""
        found = self.page.evaluate(_NODE_PROPS, [name, key])
        if found is None:
            return None
        if found["kind"] == "Uint16Array":  # viser sends point positions as float16
            return np.array(found["data"], dtype=np.uint16).view(np.float16).astype(np.float64)
        if found["kind"].endswith("Array"):
            return np.array(found["data"], dtype=np.float64 if "Float" in found["kind"] else np.int64)
        return found["data"]

    def node_points(self, name: str) -> np.ndarray | None:
        """``(N, 3)`` positions of a point cloud / line segments node (segments: 2 rows per segment)."""
        points = self.node_prop(name, "points")
        return None if points is None else points.reshape(-1, 3)

    def node_image(self, name: str) -> np.ndarray | None:
        """The RGB uint8 ``(H, W, 3)`` picture of an image node (decoded from the PNG/JPEG the page holds)."""
        data = self.node_prop(name, "_data")
        if data is None:
            return None
        decoded = cv2.imdecode(np.asarray(data, dtype=np.uint8), cv2.IMREAD_COLOR)
        return decoded[:, :, ::-1].copy()

    def screen_points(self, name: str, local_points: Any) -> np.ndarray | None:
        """Where the points ``(N, 3)`` given in node ``name``'s frame are drawn on the page now, ``(N, 2)``
        CSS px (None: the page has no such node)."""
        points = np.asarray(local_points, dtype=np.float64).reshape(-1, 3).tolist()
        found = self.page.evaluate(_PROJECT_MANY, [name, points])
        return None if found is None else np.array(found, dtype=np.float64).reshape(-1, 2)

    def on_canvas(self, points: Any) -> np.ndarray:
        """For each page point ``(x, y)``: whether a click there reaches the 3D canvas (no panel, notification
        or other element covers it)."""
        xy = np.asarray(points, dtype=np.float64).reshape(-1, 2).tolist()
        return np.array(self.page.evaluate(_ON_CANVAS, xy), dtype=bool)

    def settle(self, name: str, local_points: Any, *, timeout: float = 15.0) -> np.ndarray | None:
        """:meth:`screen_points` once they stay put (the camera glides to its framing), at most ``timeout``
        s."""
        deadline = time.monotonic() + timeout
        seen = self.screen_points(name, local_points)
        while time.monotonic() < deadline:
            self.page.wait_for_timeout(400)
            now = self.screen_points(name, local_points)
            if seen is not None and now is not None and np.allclose(now, seen, atol=0.5):
                return now
            seen = now
        return seen

    def dismiss_software_rendering_notice(self) -> None:
        """Close viser's "Software WebGL rendering detected" notice (shown without a GPU) as a user does: it
        covers the top of the scene."""
        notice = self.page.locator(".mantine-Notification-root", has_text="Software WebGL rendering detected")
        if notice.count() and notice.first.is_visible():
            notice.first.locator("button").first.click()
            notice.first.wait_for(state="hidden", timeout=WAIT_MS)

    def click_node(self, name: str, local_point: tuple[float, float, float]) -> None:
        """Click with the mouse where ``local_point`` (in node ``name``'s frame) is drawn on the canvas."""
        point = [float(v) for v in local_point]
        where = self.page.evaluate(_PROJECT, [name, point])
        assert where is not None, f"the page has no scene node {name!r}"
        # the camera may still be gliding to its framing: click once the point stays put on the canvas
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            self.page.wait_for_timeout(300)
            now = self.page.evaluate(_PROJECT, [name, point])
            if np.allclose(now, where, atol=0.5):
                break
            where = now
        self.page.mouse.click(where[0], where[1])


@pytest.fixture
def viewer_page(browser) -> Callable[[str], ViewerPage]:
    """Open a URL of the viewer in a new page of the test's browser: ``viewer_page(url) -> ViewerPage``."""

    def open_page(url: str) -> ViewerPage:
        page = browser.new_page(viewport={"width": 1400, "height": 900})
        page.goto(url, timeout=WAIT_MS)
        page.wait_for_function("() => window.__viserSceneTree !== undefined && window.__viserMutable !== "
                               "undefined",
                               timeout=WAIT_MS)
        return ViewerPage(page)

    return open_page


class LabAPI:
    """The lab's REST API as a script uses it: make a session, run steps, read values and history."""

    def __init__(self, api_url: str) -> None:
        self.url = api_url

    def create(self, module: str, dataset: str, options: dict[str, Any]) -> str:
        """A new session of ``module`` on ``dataset`` with these dataset options; returns its id."""
        body = {"module": module, "dataset": dataset, "options": options}
        created = httpx.post(f"{self.url}/api/sessions", json=body, timeout=120)
        assert created.status_code == 201, created.text
        return created.json()["id"]

    def run(self, session_id: str, step: str, controls: dict[str, Any]) -> dict[str, Any]:
        """Run ``step`` with ``controls``; returns the run record."""
        ran = httpx.post(f"{self.url}/api/sessions/{session_id}/steps/{step}", json=controls, timeout=180)
        assert ran.status_code == 200, ran.text
        return ran.json()

    def value(self, session_id: str, name: str, format: str = "json") -> Any:
        """State value ``name``: its JSON, or the raw bytes in another ``format`` (png, npy ...)."""
        answer = httpx.get(f"{self.url}/api/sessions/{session_id}/values/{name}", params={"format": format},
                           timeout=60)
        assert answer.status_code == 200, answer.text
        return answer.json() if format == "json" else answer.content

    def history(self, session_id: str) -> list[dict[str, Any]]:
        return httpx.get(f"{self.url}/api/sessions/{session_id}", timeout=30).json()["history"]


@pytest.fixture
def lab_api(lab_server) -> LabAPI:
    """The REST API of the test's lab server (``lab_server`` of ``test_browser.py``)."""
    return LabAPI(lab_server[0])


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A failed browser test leaves what its pages showed: a screenshot of each open page in ``test-output/
    failures/`` and the end of each page's text in the report (CI prints it: the log is all it keeps)."""
    outcome = yield
    report = outcome.get_result()
    if report.when != "call" or not report.failed:
        return
    browser = item.funcargs.get("browser") or item.funcargs.get("shared_browser")
    if browser is None:
        return
    folder = OUTPUT / "failures"
    folder.mkdir(parents=True, exist_ok=True)
    shown = []
    for c, context in enumerate(browser.contexts):
        for p, page in enumerate(context.pages):
            name = f"{item.name}-{c}-{p}"
            try:
                page.screenshot(path=str(folder / f"{name}.png"), timeout=10_000)
                text = page.inner_text("body", timeout=10_000)
            except Exception as exc:  # the page may be gone or hung: say so, keep the test's own failure
                text = f"(could not read the page: {exc})"
            shown.append(f"--- page {name} ({page.url}), last 3000 characters of its text:\n{text[-3000:]}")
    if shown:
        report.sections.append(("what the browser showed", "\n".join(shown)))


@pytest.fixture(scope="module")
def served_lab(tmp_path_factory):
    """The lab served as a user starts it, one for the test module; yields (api_url, viewer_url). Its log
    must hold no traceback (checked when the module's tests are done)."""
    log_path = tmp_path_factory.mktemp("lab-server") / "server.log"
    with open(log_path, "w") as log:
        yield from _serve(free_port(), free_port(), dict(os.environ, PYTHONUNBUFFERED="1"), log)
    text = log_path.read_text()
    assert "Traceback" not in text, text[-3000:]


@pytest.fixture(scope="module")
def shared_browser():
    """Headless Debian chromium, one for the test module."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()
