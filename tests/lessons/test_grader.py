"""The grader on the toy lesson: full marks, zero, exact partial credit, seeds, messages, results.json."""

from __future__ import annotations

import json

import jsonschema
import numpy as np
import pytest

from lab.core.errors import LabError
from lab.lessons.grader import DataRun, draw_seeds, grade

from lesson_helpers import submission

#: Gradescope's results.json, as the autograder documentation describes it.
RESULTS_SCHEMA = {
    "type": "object",
    "required": ["score", "execution_time", "output", "tests"],
    "properties": {
        "score": {"type": "number"},
        "execution_time": {"type": "number", "minimum": 0},
        "output": {"type": "string"},
        "extra_data": {"type": "object"},
        "tests": {"type": "array", "items": {
            "type": "object",
            "required": ["name", "score", "max_score", "status", "output", "visibility"],
            "additionalProperties": False,
            "properties": {
                "name": {"type": "string", "minLength": 1},
                "score": {"type": "number", "minimum": 0},
                "max_score": {"type": "number", "minimum": 0},
                "status": {"enum": ["passed", "failed"]},
                "output": {"type": "string", "minLength": 1},
                "visibility": {"enum": ["visible", "hidden", "after_due_date", "after_published"]},
                "extra_data": {"type": "object"},  # Gradescope keeps a test's extra_data for the instructor
            }}},
    },
}


def failed_checks(report) -> set[str]:
    return {t.name for t in report.tests if t.status == "failed"}


def test_reference_scores_full_marks(toy_lesson):
    report = grade(toy_lesson, reference=True)
    assert report.score == report.max_score == 6.0
    assert all(t.status == "passed" for t in report.tests)
    jsonschema.validate(report.results_json(), RESULTS_SCHEMA)


def test_a_correct_student_solution_scores_full_marks_and_its_prints_are_shown(toy_lesson):
    report = grade(toy_lesson, submission("toy", "solution.py"))
    assert report.score == 6.0, [t.output for t in report.tests if t.status == "failed"]
    means = next(t for t in report.tests if t.name == "Mean intensity: same means as the reference")
    assert "What your code printed:\ncomputing 3 means" in means.output


def test_the_starter_scores_zero_with_a_message_on_every_test(toy_lesson):
    report = grade(toy_lesson, toy_lesson.starter)
    assert report.score == 0.0 and len(report.tests) == 6
    for test in report.tests:
        assert test.status == "failed" and "not implemented yet" in test.output
        assert "NotImplementedError" in test.output
    jsonschema.validate(report.results_json(), RESULTS_SCHEMA)


@pytest.mark.parametrize("fixture,failed,hint", [
    ("wrong_ignores_scale.py", {"Mean intensity: scale = 3"}, "you ignore the control scale"),
    ("wrong_sums.py", {"Mean intensity: same means as the reference", "Mean intensity: scale = 3",
                       "Mean intensity: the instructor's data",
                       "Mean intensity: normalized means from yours"},
     "right up to a scale factor"),
    ("wrong_no_clip.py", {"Noisy images: same noisy images as the reference",
                          "Noisy images: the means of your noisy images"},
     "your noisy pixels leave [0, 1]: clip them"),
])
def test_wrong_implementations_lose_exactly_their_checks(toy_lesson, fixture, failed, hint):
    report = grade(toy_lesson, submission("toy", fixture))
    assert failed_checks(report) == failed
    assert report.score == report.max_score - sum(t.max_score for t in report.tests if t.name in failed)
    assert any(hint in t.output for t in report.tests if t.name in failed)


def test_a_mistake_that_fails_while_grading_costs_its_hint_not_the_grading(tmp_path, toy_lesson):
    """mistakes.py is the author's code: if one of its functions raises on the data, the check keeps its
    message without that hint, and every other check is graded as usual."""
    import shutil

    from lab.lessons.format import load_lesson

    folder = tmp_path / toy_lesson.id
    shutil.copytree(toy_lesson.path, folder)
    mistakes = folder / "mistakes.py"
    docstring = '"""Each image\'s sum instead of its mean."""'
    broken_text = '"""Broken."""\n    raise RuntimeError("broken mistake")'
    mistakes.write_text(mistakes.read_text().replace(docstring, broken_text))
    broken = load_lesson(folder)
    report = grade(broken, submission("toy", "wrong_sums.py"), seed=3)
    lost = {t.name: t.output for t in report.tests if t.status == "failed"}
    assert set(lost) == {"Mean intensity: same means as the reference", "Mean intensity: scale = 3",
                         "Mean intensity: the instructor's data",
                         "Mean intensity: normalized means from yours"}
    assert "Expected:" in lost["Mean intensity: scale = 3"]
    assert not any("you sum each image's pixels" in output for output in lost.values())
    assert "you sum each image's pixels" in "".join(t.output for t in grade(toy_lesson, submission(
        "toy", "wrong_sums.py"), seed=3).tests)


def test_messages_say_which_check_what_was_expected_and_what_came_back(toy_lesson):
    report = grade(toy_lesson, submission("toy", "wrong_ignores_scale.py"))
    test = next(t for t in report.tests if t.status == "failed")
    assert test.output.startswith("Check: scale = 3\nData: three 16 x 16 gradient images")
    assert "Controls of mean_intensity: scale=3" in test.output
    assert "Expected:" in test.output and "Got:" in test.output
    assert "Hint: you ignore the control scale: multiply by it" in test.output


def test_visibility_comes_from_the_lesson(toy_lesson):
    report = grade(toy_lesson, reference=True)
    visibilities = {t.name: t.visibility for t in report.tests}
    assert visibilities["Mean intensity: the instructor's data"] == "after_published"
    assert visibilities["Mean intensity: scale = 3"] == "visible"


def test_a_timeout_in_one_task_does_not_cost_the_next_task(toy_lesson):
    source = submission("toy", "solution.py").replace(
        "def make_noisy(images, *, sigma=0.05, rng):\n",
        "def make_noisy(images, *, sigma=0.05, rng):\n    while True:\n        pass\n")
    limits = toy_lesson.limits.replace(call_timeout_s=1.0)
    report = grade(toy_lesson, source, limits=limits)
    assert failed_checks(report) == {"Noisy images: same noisy images as the reference",
                                     "Noisy images: the means of your noisy images"}
    assert report.score == 4.0


def test_wrong_parameters_fail_the_task_with_the_signature(toy_lesson):
    source = submission("toy", "solution.py").replace("def mean_intensity(noisy, *, scale=1):",
                                                      "def mean_intensity(noisy, *, factor=1):")
    report = grade(toy_lesson, source)
    means = [t for t in report.tests if t.task == "means"]
    assert all(t.status == "failed" and "does not match the signature" in t.output for t in means)
    assert "def mean_intensity(noisy: ImageSet, *, scale: int = 1)" in means[0].output
    assert all(t.status == "passed" for t in report.tests if t.task == "noise")


# --- seeds ------------------------------------------------------------------------------------------------
def test_practice_seeds_differ_between_gradings_and_the_instructor_seed_is_kept(toy_lesson):
    first, second = draw_seeds(toy_lesson), draw_seeds(toy_lesson)
    assert first["secret"] == second["secret"] == [1234]
    assert first["small"] != second["small"]  # 1 chance in 2^31 of a false failure
    assert draw_seeds(toy_lesson, 7)["secret"] == [1234]  # a pinned dataset keeps its seed under any assignment


def test_seed_option_makes_grading_reproducible(toy_lesson):
    assert draw_seeds(toy_lesson, 7) == draw_seeds(toy_lesson, 7) != draw_seeds(toy_lesson, 8)
    one = grade(toy_lesson, submission("toy", "wrong_sums.py"), seed=7)
    two = grade(toy_lesson, submission("toy", "wrong_sums.py"), seed=7)
    assert [t.output for t in one.tests] == [t.output for t in two.tests]
    assert one.seeds == two.seeds


def test_seed_from_the_environment(toy_lesson):
    import dataclasses

    secret = dataclasses.replace(toy_lesson.datasets["secret"], seed="env:TOY_SEED")
    lesson = dataclasses.replace(toy_lesson, datasets={**toy_lesson.datasets, "secret": secret})
    assert draw_seeds(lesson, environ={"TOY_SEED": "99"})["secret"] == [99]
    with pytest.raises(LabError, match="TOY_SEED, which is not set"):
        draw_seeds(lesson, environ={})


def test_a_dataset_that_fails_for_a_seed_is_retried_with_another(toy_lesson):
    import dataclasses

    calls = []
    pipeline = toy_lesson.pipeline
    original = pipeline.dataset("gradients").loader

    def flaky(**options):
        calls.append(options["seed"])
        if len(calls) < 3:
            raise LabError("seed", "could not place the board")
        return original(**options)

    spec = pipeline.dataset("gradients")
    flaky_pipeline = dataclasses.replace(pipeline, datasets=(dataclasses.replace(spec, loader=flaky),))
    run = DataRun(flaky_pipeline, toy_lesson.datasets["small"], 5, reseed=lambda attempt: 100 + attempt)
    assert "images" in run.reference("mean_intensity").state
    assert calls == [5, 101, 102] and run.seed == 102
    fixed = DataRun(flaky_pipeline, toy_lesson.datasets["secret"], 1234, reseed=None)
    calls.clear()
    with pytest.raises(LabError, match="could not be made"):
        fixed.reference("mean_intensity")
    assert calls == [1234]


def test_a_check_dataset_runs_what_the_planner_plans_for_each_task_once(toy_lesson):
    run = DataRun(toy_lesson.pipeline, toy_lesson.datasets["small"], 5)
    session = run.reference("make_noisy")
    assert [r.step for r in session.history] == ["make_noisy"]
    assert run.reference("mean_intensity") is session and run.reference("make_noisy") is session
    assert [r.step for r in session.history] == ["make_noisy", "mean_intensity"]  # nothing twice or more
    assert session.ran_with["make_noisy"] == {"sigma": 0.05}  # the dataset's controls


def test_results_json_is_plain_json(toy_lesson):
    report = grade(toy_lesson, submission("toy", "wrong_sums.py"), seed=3)
    results = json.loads(json.dumps(report.results_json()))
    jsonschema.validate(results, RESULTS_SCHEMA)
    assert results["score"] == pytest.approx(sum(t["score"] for t in results["tests"]))
    assert results["extra_data"]["max_score"] == 6.0 and "small" in results["extra_data"]["seeds"]
    assert np.isfinite(results["execution_time"])


def test_grade_needs_a_source_or_the_reference(toy_lesson):
    with pytest.raises(LabError, match="give the submission"):
        grade(toy_lesson)
