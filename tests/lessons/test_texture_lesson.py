"""lessons/07-texture: the reference scores full marks and the starter zero, a student's own solution
scores full marks, each wrong implementation loses exactly the checks its docstring lists, and the
messages say what to fix: every check a wrong fixture fails carries the hint of its mistake
(lessons/07-texture/mistakes.py and the hints of tasks.toml), and no other mistake's.

Seeds are fixed here (``seed=``) so the tests are reproducible; graded for real, every run draws
fresh hidden seeds. Each fixture is graded once per module (:func:`graded`).
"""

from __future__ import annotations

import ast

import numpy as np
import pytest

from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules.texture import min_error_cut

from lesson_helpers import (REPO, SUBMISSIONS, assert_every_failure_names_its_mistake, failed, graded_once,
                            submission)

SEED = 20011999
WRONG = sorted(p.name for p in (SUBMISSIONS / "texture").glob("wrong_*.py"))

#: The hint (a part of its ``say`` in tasks.toml) every failed check of each wrong fixture must carry.
HINTS = {
    "wrong_greedy_cut.py": "your cut walks down greedily from the best pixel of the first row",
    "wrong_mask_ignored.py": "your distances compare the unknown pixels of the query too",
    "wrong_not_normalized.py": "divide each sum by the total weight of the known pixels",
    "wrong_row_argmin_cut.py": "your cut takes the smallest error of each row on its own",
    "wrong_unweighted.py": "your distances are the unweighted SSD",
}


@pytest.fixture(scope="module")
def texture_lesson():
    return load_lesson(REPO / "lessons" / "07-texture")


@pytest.fixture(scope="module")
def graded(texture_lesson):
    """``graded(name)``: the report of fixture ``name`` under SEED, graded once per module."""
    return graded_once(texture_lesson, "texture", SEED)


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
def test_each_wrong_implementation_loses_exactly_its_checks(graded, name):
    report = graded(name)
    expected = listed_failures(name)
    assert expected and expected <= {t.name for t in report.tests}
    lost = failed(report)
    assert set(lost) == expected
    assert report.score == 20.0 - sum(t.max_score for t in report.tests if t.name in lost)
    for output in lost.values():
        assert "Failed:" in output and ("Expected:" in output or "the reference gets" in output)


def test_the_unweighted_ssd_is_told_to_use_the_gaussian(graded):
    report = graded("wrong_unweighted.py")
    output = failed(report)["Masked, Gaussian-weighted SSD: gray sample: the reference's distances to "
                            "every window"]
    assert output.startswith("Check: gray sample: the reference's distances to every window\nData: a 24 x 24")
    assert "Hint: your distances are the unweighted SSD" in output and "sigma = w / 6.4" in output


def test_the_missing_normalization_is_recognised(graded):
    report = graded("wrong_not_normalized.py")
    output = failed(report)["Masked, Gaussian-weighted SSD: gray sample: the reference's distances to "
                            "every window"]
    assert "Hint: divide each sum by the total weight of the known pixels" in output


def test_a_jumping_cut_fails_the_connectivity_check_with_the_reference_value(graded):
    report = graded("wrong_row_argmin_cut.py")
    output = failed(report)["Minimum-error boundary cut: the cut is connected: neighbouring rows at most one "
                            "column apart"]
    assert "metric cut_max_step after running the pipeline to join_blocks" in output
    assert "the reference gets 1" in output


def test_every_wrong_fixture_has_its_hint():
    assert set(HINTS) == set(WRONG)


@pytest.mark.parametrize("name", WRONG)
def test_every_check_a_mistake_fails_says_what_to_fix(graded, name):
    """Each failed check names the mistake (same_as_mistake with lessons/07-texture/mistakes.py, or
    same_as_reference_with another control), and no other."""
    assert_every_failure_names_its_mistake(graded(name), HINTS, name)


def test_the_cut_mistakes_on_a_known_surface(texture_lesson):
    """The two wrong cuts lesson.md warns of, on a surface where each differs from the cut: the cheapest
    path avoids the 0 of the first row (its neighbours below cost 9), the greedy walk takes it."""
    errors = np.array([[5.0, 0.0, 5.0, 1.0],
                       [9.0, 9.0, 9.0, 1.0],
                       [9.0, 9.0, 9.0, 1.0],
                       [0.0, 9.0, 9.0, 1.0]])
    mistakes = texture_lesson.mistakes
    assert mistakes["cut_greedy_from_first_row"](errors).tolist() == [1, 0, 0, 0]
    assert mistakes["cut_each_row_alone"](errors).tolist() == [1, 3, 3, 0]
    assert min_error_cut(errors).tolist() == [3, 3, 3, 3]
