"""The viewer's lesson mode, lesson side: a student's file as overrides of a live session."""

from __future__ import annotations

import numpy as np
import pytest

from lab.core import open_session
from lab.core.errors import StepFailed, UnknownName
from lab.lessons.live import StudentCode, StudentCodeFailed

from lesson_helpers import submission


@pytest.fixture()
def session(toy_lesson):
    s = open_session(toy_lesson.pipeline, "gradients", {"count": 3, "size": 8, "seed": 1}, seed=1)
    s.run("make_noisy")
    return s


def test_the_students_step_runs_in_place_of_the_reference(toy_lesson, session):
    with StudentCode(toy_lesson, submission("toy", "wrong_ignores_scale.py")) as code:
        assert code.tasks() == {"make_noisy": "", "mean_intensity": ""}
        record = session.run("mean_intensity", {"scale": 2}, override=code.override("mean_intensity"))
        assert record.replaced and record.status == "ok"
        student = session.get("means").copy()
        session.run("mean_intensity", {"scale": 2})
        np.testing.assert_allclose(session.get("means"), 2 * student)


def test_compare_shows_both_outputs_and_leaves_the_session_alone(toy_lesson, session):
    before, history = dict(session.state), list(session.history)
    with StudentCode(toy_lesson, submission("toy", "wrong_ignores_scale.py")) as code:
        side = code.compare(session, "mean_intensity", {"scale": 3})
        assert side.passed is False and "largest difference" in side.message
        np.testing.assert_allclose(side.reference["means"], 3 * side.student["means"])
        right = code.compare(session, "mean_intensity", {"scale": 1})
        assert right.passed is True
    assert session.state.keys() == before.keys() and all(session.state[k] is before[k] for k in before)
    assert session.history == history and "means" not in session.metrics


def test_failures_are_step_failures_with_the_students_message(toy_lesson, session):
    with StudentCode(toy_lesson, toy_lesson.starter) as code:
        with pytest.raises(StepFailed) as caught:
            session.run("mean_intensity", override=code.override("mean_intensity"))
        assert isinstance(caught.value, StudentCodeFailed) and "not implemented yet" in caught.value.reason
        assert session.history[-1].status == "failed" and "means" not in session.state
        side = code.compare(session, "mean_intensity")
        assert side.passed is None and "not implemented" in side.message and "means" in side.reference
    with StudentCode(toy_lesson, submission("abuse", "reads_files.py")) as code, \
            pytest.raises(StudentCodeFailed, match="reading /etc/passwd is not allowed"):
        session.run("mean_intensity", override=code.override("mean_intensity"))


def test_missing_functions_and_unknown_steps(toy_lesson):
    with StudentCode(toy_lesson, submission("abuse", "missing_function.py")) as code:
        assert "defines no function 'mean_intensity'" in code.tasks()["mean_intensity"]
        with pytest.raises(StudentCodeFailed, match="defines no function"):
            code.override("mean_intensity")
        with pytest.raises(UnknownName, match="does not ask for"):
            code.override("normalize_means")
    with pytest.raises(StudentCodeFailed, match="SyntaxError"):
        StudentCode(toy_lesson, "def f(:\n")
