"""End to end, every module as a newcomer meets it: its card on the landing page opens the viewer, "Run all"
runs the whole pipeline, and then the page shows what the module is about (issue 16).

Per module: the card's "Open in the viewer" link opens a session of the module; the user unfolds the
folders of the long steps (viser cannot unfold one for them) and presses Run all; every step's label must
come to read done (a failed step fails the test with what the page says). Meanwhile a MutationObserver in
the page records each progress text shown in a long step's own folder, with the folder's label then and
whether text and bar were visible: each long step must have shown them, and while its label read running
when it ran long enough for the page to see that. After the run, the camera settled: the Scene panel's
legend lists entries (a session value's drawn at ``/lab/<name>``); the lab's 3D content (the vertices of
the visible three.js objects under ``/lab`` and ``/explore`` projected through the page's camera) lies inside
the canvas no panel covers and spans a fair share of it; the page logged no console error; the server's
log holds no traceback. Every problem found is reported at once. Screenshots, and what the test saw
(progress records, step run times, each node's screen box) as ``<module>-seen.json``, go to
``test-output/e2e-modules/``. One lab server and one browser for all modules.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import WAIT_MS, ViewerPage
from test_browser import unfold

from lab.modules import MODULES, get_pipeline

pytestmark = pytest.mark.e2e

OUTPUT = Path(__file__).resolve().parents[2] / "test-output" / "e2e-modules"
#: How long Run all may take (sfm matches every pair, diffusion trains its denoiser; 2 shared cores).
RUN_S = 300
#: The 3D content must span at least this share of the free canvas's width or height (not a speck).
MIN_SHARE = 0.3
#: Controls set in long steps before Run all, as a user on a slow machine does: numbers typed, a text picked
#: in the dropdown. Diffusion's defaults train 4000 iterations (minutes on 2 shared cores), and a batch of 48
#: is under its SMALL_WORK, so it trains on one thread (300 iterations of 512 took 88 s at load 15); NeRF's
#: MLP trains 60 s and a shorter MLP run leaves a density too faint for extract_mesh's level, while the grid
#: reaches it in a few hundred iterations (counted, not timed, so the result does not depend on the
#: machine's load); splatting trains 10 s instead of its default 60 s (what it draws is the same kind whatever
#: it reached).
QUICK: dict[str, dict[str, dict[str, float | str]]] = {
    "diffusion": {"train_denoiser": {"iterations": 300, "batch_size": 48}, "sample": {"count": 200}},
    "nerf": {"fit_image_2d": {"iterations": 100},
             "train_nerf": {"method": "grid", "iterations": 200, "budget_seconds": 0},
             "render_path": {"frames": 8}},
    "splatting": {"train_splats": {"budget_seconds": 10}, "render_path": {"frames": 8}}}
#: viser 1.1.1's Gaussian splat renderer makes three.js log this for any splats, however well formed (a viser
#: server drawing 200 unit-covariance Gaussians and nothing else logs it too): not the lab's error.
VISER_SPLAT_NOTICE = "THREE.BufferGeometry.computeBoundingSphere(): Computed radius is NaN"
#: The modules that draw GaussianSplats.
SPLAT_MODULES = ("splatting",)


def _viser_splat_notice(error: str, module: str) -> bool:
    """Whether a console error is viser's splat renderer's notice in a module that draws splats."""
    return module in SPLAT_MODULES and error.startswith(VISER_SPLAT_NOTICE)


#: A long step that ran at least this long (s) must have shown its progress while its label read running.
WATCHABLE_S = 2.0
#: Slack (CSS px) for a projected box that touches the free canvas's edge.
EDGE_PX = 2.0

#: Records every progress text shown in a long step's folder (``steps``: [step, label prefix]) in
#: ``window.__e2eProgress``: {step, label, text, visible, bar}, each distinct record once.
_WATCH_PROGRESS = """(steps) => {
  const records = [];
  const seen = new Set();
  window.__e2eProgress = records;
  const look = () => {
    const labels = document.querySelectorAll('[data-with-border="true"] > .mantine-Paper-root:first-child');
    for (const [step, prefix] of steps) {
      const label = Array.from(labels).find((l) => l.textContent.startsWith(prefix));
      if (!label) continue;
      const folder = label.parentElement;
      const text = Array.from(folder.querySelectorAll('p')).find(
        (p) => p.textContent.startsWith(step + ': iteration'));
      if (!text) continue;
      const bar = folder.querySelector('.mantine-Progress-root');
      const record = {step, label: label.textContent, text: text.textContent, visible: text.checkVisibility(),
                      bar: bar !== null && bar.checkVisibility()};
      const key = JSON.stringify(record);
      if (!seen.has(key) && records.length < 2000) { seen.add(key); records.push(record); }
    }
  };
  new MutationObserver(look).observe(document.body, {subtree: true, childList: true, characterData: true,
                                                     attributes: true});
  look();
}"""

#: Where the lab's visible 3D nodes (under /lab and /explore) are drawn: per node, the screen box (CSS px)
#: of its objects' vertices projected through the page's camera (at most 20000 per attribute; a tilted
#: frustum's world bounding box would overshoot its drawing), and how many lie behind the camera; the
#: canvas's rect, the rects of the control panel (around Run all) and of the image panel (around the Images
#: tab) where shown, and the camera's pose.
_SCREEN_BOX = """() => {
  const m = window.__viserMutable;
  const camera = m.camera;
  const rectOf = (e) => { const r = e.getBoundingClientRect();
                          return {left: r.left, top: r.top, right: r.right, bottom: r.bottom}; };
  const panelOf = (e) => {
    for (let p = e; p; p = p.parentElement) {
      const position = getComputedStyle(p).position;
      if (position === 'absolute' || position === 'fixed') return p.checkVisibility() ? rectOf(p) : null;
    }
    return null;
  };
  const named = (selector, text) => Array.from(document.querySelectorAll(selector)).find(
    (e) => e.textContent.trim() === text);
  const runAll = named('button', 'Run all');
  const imagesTab = named('[role=tab]', 'Images');
  const panels = [runAll && panelOf(runAll), imagesTab && panelOf(imagesTab)].filter((r) => r);
  const canvas = rectOf(m.canvas);
  const shown = (o) => { for (let p = o; p; p = p.parent) if (!p.visible) return false; return true; };
  const roots = new Set(Object.values(m.nodeRefFromName));
  camera.updateMatrixWorld();
  const nodes = [];
  const project = (o, into) => {  // o's vertices into the node's box; a named child is a node of its own
    if (!o.visible || (o !== into.root && roots.has(o))) return;
    if (o.geometry && !(o.material && o.material.visible === false)) {
      const held = o.geometry.attributes;  // a fat line's vertices are its segments' ends
      const attributes = o.isLineSegments2 ? [held.instanceStart, held.instanceEnd] : [held.position];
      for (let i = 0; i < (o.isInstancedMesh ? o.count : 1); i++) {
        const matrix = o.matrixWorld.clone();
        if (o.isInstancedMesh) {
          const local = o.matrixWorld.clone();
          o.getMatrixAt(i, local);
          matrix.multiply(local);
        }
        for (const attribute of attributes.filter((a) => a)) {
          const stride = Math.max(1, Math.ceil(attribute.count / 20000));
          for (let k = 0; k < attribute.count; k += stride) {
            into.vertices += 1;
            const world = camera.position.clone().fromBufferAttribute(attribute, k).applyMatrix4(matrix);
            if (world.clone().applyMatrix4(camera.matrixWorldInverse).z > -camera.near) {
              into.behind += 1;
              continue;
            }
            const ndc = world.project(camera);
            const x = canvas.left + (ndc.x + 1) / 2 * (canvas.right - canvas.left);
            const y = canvas.top + (1 - ndc.y) / 2 * (canvas.bottom - canvas.top);
            into.left = Math.min(into.left, x); into.right = Math.max(into.right, x);
            into.top = Math.min(into.top, y); into.bottom = Math.max(into.bottom, y);
          }
        }
      }
    }
    for (const child of o.children) project(child, into);
  };
  for (const [name, root] of Object.entries(m.nodeRefFromName)) {
    if (!root || !(name.startsWith('/lab/') || name.startsWith('/explore/')) || !shown(root)) continue;
    root.updateWorldMatrix(true, true);
    const node = {root, left: Infinity, top: Infinity, right: -Infinity, bottom: -Infinity, vertices: 0,
                  behind: 0};
    project(root, node);
    delete node.root;
    if (node.vertices) nodes.push({name, ...node});
  }
  nodes.sort((a, b) => a.name < b.name ? -1 : 1);
  const pose = [...camera.position.toArray(), ...camera.quaternion.toArray()];
  return {nodes, canvas, panels, camera: pose};
}"""


def _steps(module: str) -> list[tuple[str, str, bool]]:
    """(name, label prefix ``3. Title ``, long) of every step of ``module``, in order."""
    pipeline = get_pipeline(module)
    return [(spec.name, f"{index + 1}. {spec.title} ", spec.is_generator)
            for index, spec in enumerate(pipeline.steps)]


def _labels(page: Any, steps: list[tuple[str, str, bool]]) -> dict[str, str]:
    """The label each step's folder shows now (by step name; missing: not shown)."""
    shown = page.evaluate("""(prefixes) => {
      const labels = Array.from(document.querySelectorAll(
        '[data-with-border="true"] > .mantine-Paper-root:first-child')).map((l) => l.textContent);
      return prefixes.map((p) => labels.find((l) => l.startsWith(p)) || null);
    }""", [prefix for _name, prefix, _long in steps])
    return {name: label for (name, _prefix, _long), label in zip(steps, shown, strict=True)
            if label is not None}


def _wait_for_the_end(page: Any, steps: list[tuple[str, str, bool]]) -> dict[str, str]:
    """Poll the step labels until every one reads done; fail with what the page says when one reads failed,
    or when Run all does not end within :data:`RUN_S`."""
    deadline = time.monotonic() + RUN_S
    labels: dict[str, str] = {}
    while time.monotonic() < deadline:
        labels = _labels(page, steps)
        failed = [label for label in labels.values() if "✗ failed" in label]
        if failed:
            errors = page.get_by_text(re.compile(r"^Error — ")).all_inner_texts()
            pytest.fail(f"Run all failed: {failed}; the page says: {errors}")
        if len(labels) == len(steps) and all(label.endswith("✓ done") for label in labels.values()):
            return labels
        page.wait_for_timeout(500)
    errors = page.get_by_text(re.compile(r"^Error — ")).all_inner_texts()
    pytest.fail(f"Run all did not end within {RUN_S} s; the steps read: {list(labels.values())}; the page "
                f"says: {errors}")


def _free_canvas(canvas: dict[str, float], panels: list[dict[str, float]]) -> dict[str, float]:
    """The canvas's rect without the columns the panels cover (a panel right of the canvas's centre cuts its
    right side, one left of it its left side)."""
    free = dict(canvas)
    centre = (canvas["left"] + canvas["right"]) / 2
    for panel in panels:
        overlaps = panel["left"] < free["right"] and panel["right"] > free["left"] \
            and panel["top"] < free["bottom"] and panel["bottom"] > free["top"]
        if not overlaps:
            continue
        if (panel["left"] + panel["right"]) / 2 > centre:
            free["right"] = min(free["right"], panel["left"])
        else:
            free["left"] = max(free["left"], panel["right"])
    return free


def _settled_screen_box(page: Any) -> dict[str, Any]:
    """:data:`_SCREEN_BOX` once the camera stopped moving (it glides to its framing) — at most 15 s."""
    deadline = time.monotonic() + 15
    seen = page.evaluate(_SCREEN_BOX)
    while time.monotonic() < deadline:
        page.wait_for_timeout(500)
        now = page.evaluate(_SCREEN_BOX)
        if now == seen:
            return now
        seen = now
    return seen


@pytest.mark.parametrize("module", MODULES)
def test_run_all_from_the_landing_page_shows_the_module(served_lab, shared_browser, module):
    api_url, _viewer = served_lab
    steps = _steps(module)
    long_steps = [(name, prefix) for name, prefix, long in steps if long]
    OUTPUT.mkdir(parents=True, exist_ok=True)
    page = shared_browser.new_page(viewport={"width": 1400, "height": 900})
    errors: list[str] = []
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.on("pageerror", lambda error: errors.append(f"page error: {error}"))
    try:
        # the module's card on the landing page opens the viewer on a session of the module
        page.goto(api_url + "/", timeout=WAIT_MS)
        link = page.locator(f'[data-module="{module}"] .actions a', has_text="Open in the viewer")
        link.wait_for(timeout=WAIT_MS)
        assert link.get_attribute("href").endswith(f"/?module={module}")
        link.click()
        page.wait_for_url(re.compile(r".*[?&]session=\w+"), timeout=WAIT_MS)
        page.get_by_text(re.compile(rf"^{re.escape(steps[-1][1])}")).first.wait_for(timeout=WAIT_MS)

        # unfold the long steps (to watch them), watch their folders, press Run all, wait for the end
        for _name, prefix in long_steps:
            unfold(page, re.compile(rf"^{re.escape(prefix)}"), "role=button[name='Run']").wait_for(
                state="visible", timeout=WAIT_MS)
        for step, controls in QUICK.get(module, {}).items():
            prefix = dict(long_steps)[step]
            folder = page.get_by_text(re.compile(rf"^{re.escape(prefix)}")).first.locator("xpath=..")
            for control, value in controls.items():
                if isinstance(value, str):
                    ViewerPage(page).choose(folder, control, value)
                else:
                    ViewerPage(page).type_numbers(folder, control, value)
        page.evaluate(_WATCH_PROGRESS, [[name, prefix] for name, prefix in long_steps])
        page.get_by_role("button", name="Run all", exact=True).click()
        _wait_for_the_end(page, steps)
        page.wait_for_timeout(1500)  # the last drawings and legend arrive
        on_screen = _settled_screen_box(page)
        ViewerPage(page).dismiss_software_rendering_notice()
        page.screenshot(path=str(OUTPUT / f"{module}-run-all.png"))

        session_id = re.search(r"session=(\w+)", page.url).group(1)
        session = httpx.get(f"{api_url}/api/sessions/{session_id}", timeout=30).json()
        seconds = {record["step"]: record["seconds"] for record in session["history"]}
        records = page.evaluate("() => window.__e2eProgress")
        (OUTPUT / f"{module}-seen.json").write_text(json.dumps(
            {"seconds": seconds, "progress": records, "screen": on_screen}, indent=1))
        problems = _progress_problems(records, long_steps, seconds)
        problems += _legend_problems(page, module, [name for name, _prefix, _long in steps])
        problems += _framing_problems(on_screen)
        problems += [f"console error: {error}" for error in errors if not _viser_splat_notice(error, module)]
        assert not problems, f"{module}:\n" + "\n".join(problems)
    finally:
        page.screenshot(path=str(OUTPUT / f"{module}-last.png"))
        page.close()


def _progress_problems(records: list[dict[str, Any]], long_steps: list[tuple[str, str]],
                       seconds: dict[str, float]) -> list[str]:
    """What is wrong with the progress the long steps showed in their folders (``records`` of
    :data:`_WATCH_PROGRESS`; ``seconds``: how long each step's run took, from the session's history): each
    must have shown it there, text and bar visible, and while its label read running when it ran at least
    :data:`WATCHABLE_S` (a quicker run's start and end can reach the page in one update)."""
    problems = []
    for name, _prefix in long_steps:
        shown = [r for r in records if r["step"] == name and r["visible"] and r["bar"]]
        while_running = [r for r in shown if "running" in r["label"]]
        seen = [r for r in records if r["step"] == name][:3]
        if not shown:
            problems.append(f"{name}: no visible progress (text and bar) in its folder; seen: {seen}")
        elif not while_running and seconds.get(name, 0.0) >= WATCHABLE_S:
            problems.append(f"{name}: ran {seconds[name]:.1f} s but showed no progress while its label read "
                            f"running; seen: {seen}")
    return problems


def _legend_problems(page: Any, module: str, steps: Iterable[str]) -> list[str]:
    """What is wrong with the Scene panel's legend: it must list entries; one a step or the dataset wrote
    (its producer, in brackets) must be drawn at ``/lab/<name>``, one an interaction draws (the
    interaction's title) somewhere under ``/explore/<module>``."""
    legend = page.get_by_text("Scene: legend and view", exact=True).locator("xpath=..")
    entries = legend.locator("b").evaluate_all(
        "(names) => names.map((b) => [b.textContent, b.nextElementSibling && b.nextElementSibling.tagName "
        "=== 'SPAN' ? b.nextElementSibling.textContent.replace(/^\\(|\\)$/g, '') : ''])")
    if not entries:
        return [f"the legend lists nothing: {legend.inner_text()!r}"]
    nodes = page.evaluate("() => Object.keys(window.__viserSceneTree.getState())")
    writers = {*steps, "dataset"}
    explored = any(node.startswith(f"/explore/{module}/") for node in nodes)
    missing = [f"{name} ({by})" for name, by in entries if by in writers and f"/lab/{name}" not in nodes]
    undrawn = [f"{name} ({by})" for name, by in entries if by not in writers and not explored]
    problems = [f"legend entries of session values not drawn under /lab: {missing}"] if missing else []
    return problems + ([f"legend entries of interactions with nothing under /explore/{module}: {undrawn}"]
                       if undrawn else [])


def _framing_problems(seen: dict[str, Any]) -> list[str]:
    """What is wrong with the 3D content on screen (:data:`_SCREEN_BOX`): all of it must lie inside the
    canvas no panel covers and span at least :data:`MIN_SHARE` of its width or height."""
    nodes, free = seen["nodes"], _free_canvas(seen["canvas"], seen["panels"])
    if not nodes:
        return ["no 3D content drawn under /lab or /explore"]
    box = {"left": min(n["left"] for n in nodes), "top": min(n["top"] for n in nodes),
           "right": max(n["right"] for n in nodes), "bottom": max(n["bottom"] for n in nodes)}
    where = f"content {_rounded(box)}, free canvas {_rounded(free)}"
    problems = []
    out = [f"{n['name']} {_rounded(n)}" + (f" ({n['behind']}/{n['vertices']} vertices behind the camera)"
                                            if n["behind"] else "")
           for n in nodes if n["behind"] or _beyond(n, free)]
    if out:
        problems.append(f"the 3D content leaves the view (px beyond each side: {_beyond(box, free)}): "
                        f"{where}; {len(out)} of {len(nodes)} nodes out: {out[:6]}"
                        f"{' ...' if len(out) > 6 else ''}")
    width, height = free["right"] - free["left"], free["bottom"] - free["top"]
    share = max((box["right"] - box["left"]) / width, (box["bottom"] - box["top"]) / height)
    if share < MIN_SHARE:
        problems.append(f"the 3D content spans only {share:.0%} of the free canvas: {where}")
    return problems


def _beyond(box: dict[str, Any], free: dict[str, float]) -> dict[str, int]:
    """How far (px) ``box`` reaches beyond each side of ``free`` (sides within :data:`EDGE_PX` left out)."""
    over = {"left": free["left"] - box["left"], "right": box["right"] - free["right"],
            "top": free["top"] - box["top"], "bottom": box["bottom"] - free["bottom"]}
    return {side: round(px) for side, px in over.items() if px > EDGE_PX}


def _rounded(rect: dict[str, Any]) -> list[int]:
    """A rect as [left, top, right, bottom], rounded to px."""
    return [round(rect[side]) for side in ("left", "top", "right", "bottom")]
