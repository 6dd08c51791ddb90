"""For every lesson (those in lessons/ and the toy lesson of the tests): the reference scores full marks,
the starter scores zero with a message on every test, and at least three plausible wrong
implementations, kept under tests/fixtures/submissions/<lesson name>/wrong_*.py, each lose the
points of exactly the checks their docstring lists under "Fails exactly these checks", with a
message that says what was expected and a hint that says what to fix.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest

from lab.lessons.format import LessonCatalog, load_lesson, step_signature
from lab.lessons.grader import grade

from lesson_helpers import FIXTURES, REPO, SUBMISSIONS

SEED = 7

LESSON_FOLDERS = ([REPO / "lessons" / i for i in LessonCatalog(REPO / "lessons").ids()]
                  + [FIXTURES / "lessons" / "00-toy"])


def lesson_name(folder: Path) -> str:
    return folder.name.split("-", 1)[1]


def wrong_fixtures(folder: Path) -> list[Path]:
    return sorted((SUBMISSIONS / lesson_name(folder)).glob("wrong_*.py"))


def expected_failures(path: Path) -> set[str]:
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    _, _, listed = doc.partition("Fails exactly these checks")
    return {line[2:].strip() for line in listed.splitlines() if line.startswith("- ")}


CASES = [(folder, fixture) for folder in LESSON_FOLDERS for fixture in wrong_fixtures(folder)]


@pytest.fixture(scope="module")
def lessons():
    return {folder: load_lesson(folder) for folder in LESSON_FOLDERS}


def test_there_is_a_lesson_and_each_has_three_wrong_implementations():
    assert any(folder.parent == REPO / "lessons" for folder in LESSON_FOLDERS)
    for folder in LESSON_FOLDERS:
        fixtures = wrong_fixtures(folder)
        assert len(fixtures) >= 3, folder
        for fixture in fixtures:
            assert expected_failures(fixture), fixture


@pytest.mark.parametrize("folder", LESSON_FOLDERS, ids=lambda f: f.name)
def test_reference_full_marks_and_starter_zero(lessons, folder):
    lesson = lessons[folder]
    reference = grade(lesson, reference=True, seed=SEED)
    assert reference.score == reference.max_score == lesson.points
    starter = grade(lesson, lesson.starter, seed=SEED)
    assert starter.score == 0.0
    assert all(t.status == "failed" and "NotImplementedError" in t.output for t in starter.tests)


@pytest.mark.parametrize("folder", LESSON_FOLDERS, ids=lambda f: f.name)
def test_every_lesson_writes_each_fact_once(lessons, folder):
    """Signatures come from the steps, points from the checks, and every hint is defined once and used."""
    lesson = lessons[folder]
    assert lesson.warnings == ()
    raw = tomllib.loads((folder / "tasks.toml").read_text())
    for task, table in zip(lesson.tasks, raw["tasks"], strict=True):
        assert "signature" not in table and "points" not in table
        assert task.signature == step_signature(lesson.pipeline.step(task.step))
        assert task.points == sum(c.points for c in task.checks)
        for check in table["checks"]:
            assert all(isinstance(name, str) for name in check.get("hints", []))
    named = {rule.name for task in lesson.tasks for check in task.checks for rule in check.hints}
    assert set(raw.get("hints", {})) <= named


@pytest.mark.parametrize("folder,fixture", CASES, ids=[f"{f.name}-{p.stem}" for f, p in CASES])
def test_wrong_implementation_loses_exactly_its_checks(lessons, folder, fixture):
    lesson = lessons[folder]
    report = grade(lesson, fixture.read_text(), seed=SEED)
    names = {t.name for t in report.tests}
    expected = expected_failures(fixture)
    assert expected <= names, expected - names  # the docstring names real checks
    lost = {t.name: t for t in report.tests if t.status == "failed"}
    assert set(lost) == expected
    assert report.score == lesson.points - sum(t.max_score for t in lost.values())
    for test in lost.values():
        assert "Failed:" in test.output
        assert "Expected:" in test.output or "the reference gets" in test.output
        assert "\nHint: " in test.output, f"{test.name}: no hint says what to fix (a detector or mistakes.py)"
