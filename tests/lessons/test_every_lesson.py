"""For every lesson (those in lessons/ and the toy lesson of the tests): the reference scores full marks,
the starter scores zero with a message on every test, and at least three plausible wrong
implementations, kept under tests/fixtures/submissions/<lesson name>/wrong_*.py, each lose the
points of exactly the checks their docstring lists under "Fails exactly these checks", with a
message that says what was expected and a hint that says what to fix.

Grades an instructor can defend (issue 15): each wrong fixture names the hints that name its cause
(a line ``# cause: name, ...``); across all of them at least 80 % of the failed checks carry one of
those hints and none carries another. Correct-but-different fixtures (``correct_*.py``) score full
marks. A regrade with the same assignment seed gives the same score and messages, in whatever order
the variants of the data are graded. Every lesson validates under mutation testing
(:mod:`lab.lessons.validate`): no check that no mutant fails, no mutant no check catches.
"""

from __future__ import annotations

import ast
import re
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


def causes(path: Path) -> set[str]:
    """The hint names a fixture's ``# cause: a, b`` line gives (what correctly names its mistake); a mutant
    with arguments may be named whole, ``swapped(x1, x2)``, or by its kind, ``swapped``."""
    for line in path.read_text().splitlines():
        head, _, names = line.lstrip("# ").partition("cause:")
        if not head.strip() and names:
            return {name.strip() for name in re.split(r",(?![^(]*\))", names) if name.strip()}
    return set()


def named(hints, fixture: Path) -> set[str]:
    """The hints (of a test) that name one of the fixture's causes."""
    wanted = causes(fixture)
    return {h for h in hints if h in wanted or h.split("(")[0] in wanted}


def correct_fixtures(folder: Path) -> list[Path]:
    return sorted((SUBMISSIONS / lesson_name(folder)).glob("correct_*.py"))


def expected_failures(path: Path) -> set[str]:
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    _, _, listed = doc.partition("Fails exactly these checks")
    return {line[2:].strip() for line in listed.splitlines() if line.startswith("- ")}


CASES = [(folder, fixture) for folder in LESSON_FOLDERS for fixture in wrong_fixtures(folder)]


@pytest.fixture(scope="module")
def lessons():
    return {folder: load_lesson(folder) for folder in LESSON_FOLDERS}


@pytest.fixture(scope="module")
def graded(lessons):
    """``graded(folder, fixture)``: the fixture's grade under SEED, graded once per test module."""
    reports: dict = {}

    def report(folder: Path, fixture: Path):
        if (folder, fixture) not in reports:
            reports[folder, fixture] = grade(lessons[folder], fixture.read_text(), seed=SEED)
        return reports[folder, fixture]

    return report


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
def test_wrong_implementation_loses_exactly_its_checks(lessons, graded, folder, fixture):
    lesson = lessons[folder]
    report = graded(folder, fixture)
    names = {t.name for t in report.tests}
    expected = expected_failures(fixture)
    assert expected <= names, expected - names  # the docstring names real checks
    lost = {t.name: t for t in report.tests if t.status == "failed"}
    assert set(lost) == expected
    assert report.score == lesson.points - sum(t.max_score for t in lost.values())
    for test in lost.values():
        said = ("Expected:", "the reference gets", "wrong form", "could not", "failed on your output")
        assert any(s in test.output for s in said), test.output
        assert "\nHint: " in test.output, f"{test.name}: no hint says what to fix (a detector or mistakes.py)"
        wrong = set(test.hints) - named(test.hints, fixture)
        assert not wrong, f"{test.name}: hint {sorted(wrong)} names another mistake than {sorted(causes(fixture))}"
        assert "Not graded" not in test.output


def test_at_least_80_percent_of_the_failed_checks_name_the_cause(graded):
    """Across every lesson's wrong fixtures: the share of failed checks whose hints include one of the
    fixture's causes (and, by the test above, no other)."""
    naming, failed_checks, unnamed = 0, 0, []
    for folder, fixture in CASES:
        assert causes(fixture), f"{fixture}: give a line '# cause: <hint name>, ...'"
        for test in graded(folder, fixture).tests:
            if test.status == "failed":
                failed_checks += 1
                if named(test.hints, fixture):
                    naming += 1
                else:
                    unnamed.append(f"{fixture.parent.name}/{fixture.name}: {test.name} {list(test.hints)}")
    print(f"\n{naming} of {failed_checks} failed checks name their cause; not named: {unnamed}")
    assert naming >= 0.8 * failed_checks, unnamed


CORRECT = [(folder, fixture) for folder in LESSON_FOLDERS for fixture in correct_fixtures(folder)]


@pytest.mark.parametrize("folder,fixture", CORRECT, ids=[f"{f.name}-{p.stem}" for f, p in CORRECT])
def test_correct_but_different_code_gets_full_marks(lessons, graded, folder, fixture):
    report = graded(folder, fixture)
    assert report.score == lessons[folder].points, {t.name: t.output for t in report.tests
                                                   if t.status == "failed"}


@pytest.mark.parametrize("folder", LESSON_FOLDERS, ids=lambda f: f.name)
def test_a_regrade_gives_the_same_score_and_messages_in_any_variant_order(lessons, graded, folder):
    """The assignment seed fixes every variant's data: grading a file again, or grading the variants of each
    dataset in reverse order, gives the same tests."""
    lesson = lessons[folder]
    fixture = wrong_fixtures(folder)[0]
    first = graded(folder, fixture)
    again = grade(lesson, fixture.read_text(), seed=SEED, variant_order=lambda count: list(range(count))[::-1])
    assert [(t.name, t.score, t.output) for t in again.tests] == [(t.name, t.score, t.output) for t in first.tests]
    assert again.seeds == first.seeds and not first.practice


@pytest.mark.parametrize("folder", LESSON_FOLDERS, ids=lambda f: f.name)
def test_every_lesson_validates_under_mutation(lessons, folder):
    from lab.lessons.validate import mutation_report

    report = mutation_report(lessons[folder])
    print("\n" + report.text())
    assert report.ok, "\n".join(report.problems)
