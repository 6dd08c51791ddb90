"""End to end, every lesson as a student finds it: the landing page's card opens the viewer's lesson mode,
"Load starter.py" loads the starter (every task unimplemented), "Run to here" on the first task step runs
the steps before it and then the student's code, and that step reads failed, with the failure shown
without unfolding it. Screenshots go to the test's tmp dir. One lab server and one browser for all."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import pytest
from test_browser import TIMEOUT_MS, unfold

from lab.lessons.format import LessonCatalog

ROOT = Path(__file__).resolve().parents[2]
CATALOG = LessonCatalog(ROOT / "lessons")
LESSONS = CATALOG.ids()

pytestmark = pytest.mark.e2e
#: How long the steps before a task may take to run (diffusion trains its denoiser first; 2 shared cores).
RUN_MS = 240_000


def _label(number: int, title: str, status: str) -> re.Pattern[str]:
    return re.compile(rf"^{number}\. {re.escape(title)} .*{status}")


#: Controls a student may turn down to get to the task sooner (typed into the steps' number boxes); a batch
#: of 48 is under diffusion's SMALL_WORK: one torch thread, not two contending ones.
QUICK = {"08-diffusion": {"train_denoiser": {"iterations": 300, "batch_size": 48}, "sample": {"count": 200}}}


def _type_controls(page, pipeline, controls: dict[str, dict[str, float]]) -> None:
    names = [spec.name for spec in pipeline.steps]
    for step, values in controls.items():
        label = _label(names.index(step) + 1, pipeline.step(step).title, "")
        for name, value in values.items():
            box = unfold(page, label, f"xpath=.//label[normalize-space()='{name}']"
                                      "/ancestor::div[.//input[@type='text']][1]//input[@type='text']")
            box.fill(f"{value:g}")
            box.press("Enter")


def _run_to_here(page, label: re.Pattern[str]) -> None:
    """Press Run to here in the step folder labelled ``label``."""
    unfold(page, label, "role=button[name='Run to here']").click()


@pytest.mark.parametrize("lesson_id", LESSONS)
def test_a_lesson_card_opens_lesson_mode_and_the_starter_fails_visibly(served_lab, shared_browser, lesson_id,
                                                                          tmp_path):
    api_url, _viewer = served_lab
    lesson = CATALOG.get(lesson_id)
    task = lesson.tasks[0]
    names = [spec.name for spec in lesson.pipeline.steps]
    number, title = names.index(task.step) + 1, lesson.pipeline.step(task.step).title
    page = shared_browser.new_page(viewport={"width": 1400, "height": 900})
    errors: list[str] = []
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    try:
        page.goto(api_url + "/", timeout=TIMEOUT_MS)
        link = page.locator(f'[data-lesson="{lesson_id}"] a.open-lesson')
        link.wait_for(timeout=TIMEOUT_MS)
        assert link.get_attribute("href").endswith(f"/?lesson={lesson_id}")
        assert lesson.module_title in page.locator(f'[data-lesson="{lesson_id}"]').inner_text()
        link.click()
        page.wait_for_url(re.compile(rf".*[?&]lesson={re.escape(lesson_id)}.*"), timeout=TIMEOUT_MS)
        page.get_by_text(_label(number, title, "(ready|blocked)")).first.wait_for(timeout=TIMEOUT_MS)

        page.get_by_role("button", name="Load starter.py", exact=True).click()
        page.get_by_text("Loaded starter.py:").wait_for(timeout=TIMEOUT_MS)
        _type_controls(page, lesson.pipeline, QUICK.get(lesson_id, {}))
        _run_to_here(page, _label(number, title, "(ready|blocked)"))

        failed = page.get_by_text(_label(number, title, "✗ failed")).first
        failed.wait_for(timeout=RUN_MS)
        failed.click()  # fold it again: the failure still shows, in the label and the lesson panel
        page.get_by_text("Your code failed", exact=False).first.wait_for(state="visible", timeout=TIMEOUT_MS)
        page.screenshot(path=str(tmp_path / f"{lesson_id}-failed.png"))
        session_id = re.search(r"session=(\w+)", page.url).group(1)
        history = httpx.get(f"{api_url}/api/sessions/{session_id}", timeout=30).json()["history"]
        last = history[-1]
        assert (last["step"], last["status"], last["replaced"]) == (task.step, "failed", True)
        assert errors == []
    finally:
        page.screenshot(path=str(tmp_path / f"{lesson_id}-last.png"))
        page.close()
