"""Paths and helpers shared by the lesson tests (imported by name: conftest modules are not importable safely)."""

from __future__ import annotations

import sys
from pathlib import Path

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
SUBMISSIONS = FIXTURES / "submissions"
REPO = Path(__file__).resolve().parents[2]

if str(FIXTURES) not in sys.path:  # the toy lesson's module "toy_lesson_pipeline:PIPELINE"
    sys.path.insert(0, str(FIXTURES))


def submission(*parts: str) -> str:
    """The text of a fixture submission, e.g. ``submission("toy", "solution.py")``."""
    return SUBMISSIONS.joinpath(*parts).read_text(encoding="utf-8")


def failed(report) -> dict[str, str]:
    """The failed tests of a grade report, name -> output."""
    return {t.name: t.output for t in report.tests if t.status == "failed"}


def hint_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("Hint: ")]


def graded_once(lesson, folder: str, seed: int):
    """``report(name)``: fixture ``submissions/<folder>/<name>`` graded under ``seed``, once per ``graded_once``."""
    from lab.lessons.grader import grade

    reports = {}

    def report(name: str):
        if name not in reports:
            reports[name] = grade(lesson, submission(folder, name), seed=seed)
        return reports[name]

    return report


def assert_every_failure_names_its_mistake(report, hints: dict[str, str], name: str) -> None:
    """Every check fixture ``name`` fails carries its hint ``hints[name]`` and no other fixture's."""
    lost = failed(report)
    assert lost
    for check, output in lost.items():
        found = hint_lines(output)
        assert any(hints[name] in line for line in found), f"{check}: {output}"
        for other, hint in hints.items():
            if other != name:
                assert not any(hint in line for line in found), f"{check} got the hint of {other}"


def wait_done(client, submission_id: str, timeout: float = 30.0) -> dict:
    """Poll ``GET /api/submissions/{id}`` until it is graded (done or error); its body."""
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        body = client.get(f"/api/submissions/{submission_id}").json()
        if body["status"] in ("done", "error"):
            return body
        time.sleep(0.05)
    raise AssertionError(f"submission {submission_id} not graded in {timeout} s")
