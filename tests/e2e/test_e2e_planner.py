"""End to end: what the viewer's buttons run and what its step list says, in headless chromium.

A calibration session made over REST opens at ``?session=ID``. **Run all** runs every step once and each
shows done. Ticking a control of a done step (``zero_skew`` of estimate_intrinsics) marks that step and
every step downstream of it stale at once, with a note naming the control, while the steps upstream stay
done and nothing runs. **Run** on the changed step re-runs it and then exactly its dependants (the REST
history says which, with the new control), and all show done again. On a texture session, **Run to here**
on ``quilt``, which reads only ``sample``, runs quilt alone (not the six lesson micro-steps listed before
it). Uses the lab server and browser fixtures of ``test_browser.py`` and ``lab_api`` / ``viewer_page`` of
``conftest.py``; screenshots go to ``test-output/``.
"""

from __future__ import annotations

import re

import httpx
import pytest
from test_browser import OUTPUT, TIMEOUT_MS, browser, lab_server  # noqa: F401  (fixtures)

CHANGED = "estimate_intrinsics"  # step 3 of calibration: its control zero_skew; steps 1-2 are upstream


def module_steps(api_url: str, module: str) -> list[dict]:
    return httpx.get(f"{api_url}/api/modules/{module}", timeout=30).json()["steps"]


def step_label(page, number: int, title: str, status: str):
    """The folder label of step ``number`` while it shows ``status``."""
    return page.get_by_text(re.compile(rf"^{number}\. {re.escape(title)} . {status}$"))


def step_folder(page, number: int, title: str):
    """The folder of step ``number`` (its label and everything inside), whatever status it shows."""
    return step_label(page, number, title, r"\w+").locator("xpath=..")


def wait_statuses(page, steps: list[dict], statuses: dict[str, str]) -> None:
    for number, step in enumerate(steps, start=1):
        if step["name"] in statuses:
            step_label(page, number, step["title"], statuses[step["name"]]).wait_for(timeout=TIMEOUT_MS)


@pytest.mark.e2e
def test_run_all_stale_marking_and_run_reruns_the_dependants(lab_server, lab_api, viewer_page):  # noqa: F811
    api_url, viewer_url = lab_server
    steps = module_steps(api_url, "calibration")
    names = [s["name"] for s in steps]
    session_id = lab_api.create("calibration", "synthetic", {})
    view = viewer_page(f"{viewer_url}/?session={session_id}")
    page = view.page
    wait_statuses(page, steps, {names[0]: "ready", names[1]: "blocked"})

    # Run all: every step once, all done
    page.get_by_role("button", name="Run all", exact=True).click()
    wait_statuses(page, steps, {name: "done" for name in names})
    assert [r["step"] for r in lab_api.history(session_id)] == names
    assert all(r["status"] == "ok" for r in lab_api.history(session_id))

    # change a control of a done step: it and its dependants are stale at once, nothing runs
    index = names.index(CHANGED)
    downstream = names[index:]
    step_label(page, index + 1, steps[index]["title"], "done").click()  # open its folder
    folder = step_folder(page, index + 1, steps[index]["title"])
    folder.get_by_label("zero_skew", exact=True).check()
    wait_statuses(page, steps, {**{name: "done" for name in names[:index]},
                                **{name: "stale" for name in downstream}})
    folder.get_by_text(re.compile(r"Stale: its controls changed since it ran: zero_skew no → yes")).wait_for(
        timeout=TIMEOUT_MS)
    assert len(lab_api.history(session_id)) == len(names)  # marking ran nothing
    page.mouse.move(700, 450)  # no hint over the note
    folder.scroll_into_view_if_needed()
    page.wait_for_timeout(500)
    page.screenshot(path=str(OUTPUT / "e2e-planner-stale.png"))

    # Run on the changed step: it and exactly its dependants re-run, with the new control; all done
    folder.get_by_role("button", name="Run", exact=True).click()
    wait_statuses(page, steps, {name: "done" for name in names})
    history = lab_api.history(session_id)
    rerun = history[len(names):]
    assert [r["step"] for r in rerun] == downstream
    assert rerun[0]["params"]["zero_skew"] is True and all(r["status"] == "ok" for r in rerun)
    assert not folder.get_by_text(re.compile(r"Stale: its controls changed")).is_visible()
    page.wait_for_timeout(1000)
    page.screenshot(path=str(OUTPUT / "e2e-planner-rerun.png"))


@pytest.mark.e2e
def test_run_to_here_on_quilt_runs_only_quilt(lab_server, lab_api, viewer_page):  # noqa: F811
    api_url, viewer_url = lab_server
    steps = module_steps(api_url, "texture")
    names = [s["name"] for s in steps]
    number = names.index("quilt") + 1
    assert number > 1  # lesson micro-steps are listed before it
    session_id = lab_api.create("texture", "procedural", {"size": 32})
    view = viewer_page(f"{viewer_url}/?session={session_id}")
    page = view.page
    step_label(page, number, steps[number - 1]["title"], "ready").click()  # open its folder
    folder = step_folder(page, number, steps[number - 1]["title"])
    folder.get_by_role("button", name="Run to here", exact=True).click()
    step_label(page, number, steps[number - 1]["title"], "done").wait_for(timeout=TIMEOUT_MS)
    assert [r["step"] for r in lab_api.history(session_id)] == ["quilt"]
    # the micro-steps did not run
    step_label(page, 1, steps[0]["title"], "ready").wait_for(timeout=TIMEOUT_MS)
    page.wait_for_timeout(1000)
    page.screenshot(path=str(OUTPUT / "e2e-planner-quilt.png"))
