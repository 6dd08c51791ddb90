"""lessons/01-calibration beyond the generic checks of test_every_lesson.py: a student's own correct
solution scores full marks (and how long grading takes), and the messages the wrong
implementations get say what to fix.

Seeds are fixed here (``seed=``) so the tests are reproducible; graded for real, every run draws
fresh hidden seeds.
"""

from __future__ import annotations

import time

from lab.lessons.grader import grade

from lesson_helpers import submission

SEED = 20240917


def failed(report) -> dict[str, str]:
    return {t.name: t.output for t in report.tests if t.status == "failed"}


def test_a_student_solution_scores_full_marks_and_grading_time_is_reported(calibration_lesson):
    started = time.perf_counter()
    report = grade(calibration_lesson, submission("calibration", "solution.py"), seed=SEED)
    seconds = time.perf_counter() - started
    print(f"\ngrading one calibration submission took {seconds:.1f} s (the issue asks for under 30 s)")
    assert report.score == 20.0, failed(report)


def test_the_unnormalized_dlt_is_told_what_to_fix(calibration_lesson):
    report = grade(calibration_lesson, submission("calibration", "wrong_unnormalized_dlt.py"), seed=SEED)
    (output,) = failed(report).values()
    assert output.startswith("Check: noisy data: the normalized DLT's homographies, up to scale\n"
                             "Data: 8 synthetic")
    assert "relative difference after the best scale factor" in output and "allowed 0.0001" in output
    assert "Hint: your homographies are what the DLT gives without normalization" in output
    assert "mean distance is sqrt(2)" in output


def test_the_transposed_homography_is_recognised(calibration_lesson):
    report = grade(calibration_lesson, submission("calibration", "wrong_transposed_homography.py"), seed=SEED)
    lost = failed(report)
    plain = lost["Normalized DLT homography: normalize = false: the plain DLT's homographies, up to scale"]
    assert "Hint: your matrix is the expected one transposed" in plain
    poses = lost["Normalized DLT homography: clean data: the camera poses computed from your homographies, "
                 "within 0.5 degrees of the truth"]
    assert "metric rotation_error_max_deg after running the pipeline to estimate_extrinsics" in poses
    assert "needed at most 0.5 (the reference gets" in poses


def test_the_dropped_skew_is_recognised(calibration_lesson):
    report = grade(calibration_lesson, submission("calibration", "wrong_skew_dropped.py"), seed=SEED)
    (output,) = failed(report).values()
    assert "at index [0, 1]" in output
    assert "Expected:\n[[" in output and "Got:\n[[" in output
    assert "Hint: your skew K[0, 1] is exactly 0 but zero_skew is false" in output
