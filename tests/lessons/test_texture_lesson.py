"""lessons/07-texture: the reference scores full marks and the starter zero, a student's own solution
scores full marks, each wrong implementation loses exactly the checks its docstring lists, and the
messages say what to fix.

Seeds are fixed here (``seed=``) so the tests are reproducible; graded for real, every run draws
fresh hidden seeds.
"""

from __future__ import annotations

import ast

import pytest

from lab.lessons.format import load_lesson
from lab.lessons.grader import grade

from lesson_helpers import REPO, SUBMISSIONS, submission

SEED = 20011999
WRONG = sorted(p.name for p in (SUBMISSIONS / "texture").glob("wrong_*.py"))


@pytest.fixture(scope="module")
def texture_lesson():
    return load_lesson(REPO / "lessons" / "07-texture")


def failed(report) -> dict[str, str]:
    return {t.name: t.output for t in report.tests if t.status == "failed"}


def listed_failures(name: str) -> set[str]:
    doc = ast.get_docstring(ast.parse(submission("texture", name))) or ""
    return {line[2:].strip() for line in doc.partition("Fails exactly these checks")[2].splitlines()
            if line.startswith("- ")}


def test_the_lesson_has_two_tasks_on_steps_of_the_texture_module(texture_lesson):
    assert texture_lesson.module == "texture" and texture_lesson.points == 20.0
    assert [t.step for t in texture_lesson.tasks] == ["window_distances", "min_error_cut"]
    assert len(WRONG) >= 3


def test_reference_full_marks_and_starter_zero(texture_lesson):
    reference = grade(texture_lesson, reference=True, seed=SEED)
    assert reference.score == reference.max_score == 20.0
    starter = grade(texture_lesson, texture_lesson.starter, seed=SEED)
    assert starter.score == 0.0
    assert all(t.status == "failed" and "NotImplementedError" in t.output for t in starter.tests)


def test_a_student_solution_scores_full_marks(texture_lesson):
    report = grade(texture_lesson, submission("texture", "solution.py"), seed=SEED)
    assert report.score == 20.0, failed(report)


@pytest.mark.parametrize("name", WRONG)
def test_each_wrong_implementation_loses_exactly_its_checks(texture_lesson, name):
    report = grade(texture_lesson, submission("texture", name), seed=SEED)
    expected = listed_failures(name)
    assert expected and expected <= {t.name for t in report.tests}
    lost = failed(report)
    assert set(lost) == expected
    assert report.score == 20.0 - sum(t.max_score for t in report.tests if t.name in lost)
    for output in lost.values():
        assert "Failed:" in output and ("Expected:" in output or "the reference gets" in output)


def test_the_unweighted_ssd_is_told_to_use_the_gaussian(texture_lesson):
    report = grade(texture_lesson, submission("texture", "wrong_unweighted.py"), seed=SEED)
    output = failed(report)["Masked, Gaussian-weighted SSD: gray sample: the reference's distances to every window"]
    assert output.startswith("Check: gray sample: the reference's distances to every window\nData: a 24 x 24")
    assert "Hint: your distances are the unweighted SSD" in output and "sigma = w / 6.4" in output


def test_the_missing_normalization_is_recognised(texture_lesson):
    report = grade(texture_lesson, submission("texture", "wrong_not_normalized.py"), seed=SEED)
    output = failed(report)["Masked, Gaussian-weighted SSD: gray sample: the reference's distances to every window"]
    assert "Hint: divide each sum by the total weight of the known pixels" in output


def test_a_jumping_cut_fails_the_connectivity_check_with_the_reference_value(texture_lesson):
    report = grade(texture_lesson, submission("texture", "wrong_row_argmin_cut.py"), seed=SEED)
    output = failed(report)["Minimum-error boundary cut: the cut is connected: neighbouring rows at most one "
                            "column apart"]
    assert "metric cut_max_step after running the pipeline to join_blocks" in output
    assert "the reference gets 1" in output
