"""lessons/03-stereo beyond the generic checks of test_every_lesson.py: a student's own correct solution
scores full marks (and how long grading takes), the starter scores zero, and the messages the wrong
implementations get say what to fix.

Seeds are fixed here (``seed=``) so the tests are reproducible; graded for real, the synthetic pair
gets a fresh hidden seed at every run.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from lab.core import Image
from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules.stereo import cost_volume, left_right_check, winner_take_all

from lesson_helpers import REPO, failed, submission

SEED = 20261122

COST = "SSD and NCC cost volumes"
LR = "Left-right consistency check"


@pytest.fixture(scope="module")
def stereo_lesson():
    return load_lesson(REPO / "lessons" / "03-stereo")


def test_the_lesson_grades_the_three_steps_of_block_matching(stereo_lesson):
    assert stereo_lesson.module == "stereo" and stereo_lesson.points == 20.0
    assert [t.step for t in stereo_lesson.tasks] == ["cost_volume", "winner_take_all", "left_right_check"]
    assert {d.dataset for d in stereo_lesson.datasets.values()} == {"synthetic", "motorcycle"}
    assert stereo_lesson.datasets["synthetic"].seed == "fresh"


def test_reference_full_marks_and_starter_zero(stereo_lesson):
    assert grade(stereo_lesson, reference=True, seed=SEED).score == 20.0
    starter = grade(stereo_lesson, stereo_lesson.starter, seed=SEED)
    assert starter.score == 0.0
    assert all("NotImplementedError" in t.output for t in starter.tests)


def test_a_student_solution_scores_full_marks_and_grading_time_is_reported(stereo_lesson):
    started = time.perf_counter()
    report = grade(stereo_lesson, submission("stereo", "solution.py"), seed=SEED)
    seconds = time.perf_counter() - started
    print(f"\ngrading one stereo submission took {seconds:.1f} s")
    assert report.score == 20.0, failed(report)


def test_the_missing_window_aggregation_is_told_what_to_fix(stereo_lesson):
    report = grade(stereo_lesson, submission("stereo", "wrong_no_window_aggregation.py"), seed=SEED)
    lost = failed(report)
    assert set(lost) == {t.name for t in report.tests if t.name.startswith(COST)}
    ssd = lost[f"{COST}: synthetic pair, SSD over 5 x 5 windows: the reference's cost volume"]
    assert ssd.startswith("Check: synthetic pair, SSD over 5 x 5 windows: the reference's cost volume\n"
                          "Data: a rendered rectified pair")
    assert "Expected:\n" in ssd and "Got:\n" in ssd
    assert "Hint: your costs are those of single pixels (window = 1)" in ssd
    ncc = lost[f"{COST}: motorcycle, NCC over 5 x 5 windows: the reference's cost volume (1 - NCC)"]
    assert "every window is flat and NCC is 0" in ncc
    wta = lost[f"{COST}: synthetic pair, SSD: winner-take-all on your cost volume is as accurate as on the "
               "reference's (bad-2 over all pixels)"]
    assert "metric bad2_all after running the pipeline to winner_take_all on your cost_volume" in wta
    assert "Hint: your costs are those of single pixels" in wta


def test_the_window_sum_instead_of_the_mean_is_recognised(stereo_lesson):
    report = grade(stereo_lesson, submission("stereo", "wrong_ssd_sum_not_mean.py"), seed=SEED)
    lost = failed(report)
    assert len(lost) == 2 and report.score == 16.0  # winner-take-all does not see the factor
    for output in lost.values():
        assert ("Hint: your SSD is the window's sum, the lab's is its mean: divide by window * window"
                in output)


def test_the_exact_left_right_match_is_recognised(stereo_lesson):
    report = grade(stereo_lesson, submission("stereo", "wrong_lr_check_exact_match.py"), seed=SEED)
    lost = failed(report)
    assert all(name.startswith(LR) for name in lost) and len(lost) == 3
    mask = lost[f"{LR}: synthetic pair, max_difference = 1: the reference's mask"]
    assert "Hint: your mask keeps only pixels whose two disparities are equal" in mask
    assert f"{LR}: synthetic pair, max_difference = 0: the reference's mask" not in lost
    pipeline = lost[f"{LR}: synthetic pair: the filtered disparity map built on your mask, bad-2 over all "
                    "pixels as the reference's"]
    assert "after running the pipeline to filter_disparity on your consistent" in pipeline


@pytest.mark.parametrize("fixture,task,hint", [
    ("wrong_cost_shift_direction.py", COST, "your volume compares left pixel x with right pixel x + d"),
    ("wrong_wta_argmax.py", "Winner-take-all", "you keep the disparity of the highest cost"),
    ("wrong_lr_check_direction.py", LR, "you read the right image's disparity at x + d_L"),
])
def test_mistakes_visible_only_in_the_steps_inputs_are_named(stereo_lesson, other_mistakes, fixture, task,
                                                              hint):
    """lessons/03-stereo/mistakes.py: the grader runs the known wrong implementation on the same inputs, so
    a shift the wrong way or an argmax gets its hint on every check it fails, and on no other."""
    report = grade(stereo_lesson, submission("stereo", fixture), seed=SEED)
    lost = failed(report)
    assert lost and all(name.startswith(task) for name in lost)
    for output in lost.values():
        assert f"Hint: {hint}" in output
    assert hint not in other_mistakes


@pytest.fixture(scope="module")
def other_mistakes(stereo_lesson) -> str:
    """What two other wrong submissions are told: no hint about a shift direction or an argmax."""
    others = ("wrong_no_window_aggregation.py", "wrong_lr_check_exact_match.py")
    reports = [grade(stereo_lesson, submission("stereo", other), seed=SEED) for other in others]
    return "".join(output for report in reports for output in failed(report).values())


def test_the_lessons_conventions_are_the_modules():
    """What lesson.md and starter.py promise, on a tiny pair: flat NCC windows cost 1, ties take the first
    disparity, and a match left of the right image fails the check."""
    flat = Image(np.full((9, 12), 0.5, np.float32))
    volume = cost_volume(flat, flat, cost="ncc", window=3, max_disparity=4)
    np.testing.assert_array_equal(volume, 1.0)
    assert np.all(winner_take_all(volume) == 0)
    consistent = left_right_check(volume, np.full((9, 12), 2), max_difference=2)  # d_R = 0 on ties
    assert not consistent[:, :2].any() and consistent[:, 2:].all()
