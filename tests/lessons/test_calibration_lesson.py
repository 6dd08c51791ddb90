"""lessons/01-calibration beyond the generic checks of test_every_lesson.py: correct solutions written
differently score full marks on several assignment seeds (and how long grading takes), every wrong
implementation loses exactly the checks it should with a hint that names its cause, and the data
exercises the rules the checks are named for (partial boards in random order, where ids matter).

The assignment seed is fixed here (``seed=``), as the server fixes one per lesson.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from lab.core import open_session
from lab.lessons.grader import grade
from lab.modules.calibration import PIPELINE, estimate_homographies

from lesson_helpers import failed, graded_once, hint_lines, submission

SEED = 20240917
SEEDS = (SEED, 3, 11)

HOMOGRAPHY = "Normalized DLT homography: "
INTRINSICS = "Closed-form intrinsics: "
CLEAN_H = HOMOGRAPHY + "clean data: the reference's homographies, up to scale"
NOISY_H = HOMOGRAPHY + "noisy data: the normalized DLT's homographies, up to scale"
PLAIN_H = HOMOGRAPHY + "normalize = false: the plain DLT's homographies, each with H[2, 2] = 1"
SCALE_H = HOMOGRAPHY + "scale: each H with H[2, 2] = 1"
POSES_H = (HOMOGRAPHY + "clean data: the camera poses computed from your homographies, within 0.5 degrees "
           "of the truth")
NOISY_K = INTRINSICS + "noisy data: the reference's K, skew estimated (zero_skew = false)"
ZERO_SKEW_K = INTRINSICS + "noisy data with zero_skew = true: the reference's K"
ALL_H = {CLEAN_H, NOISY_H, PLAIN_H, SCALE_H, POSES_H}

#: wrong fixture -> (the checks it loses, the hint names that may name its cause; every failed check carries
#: at least one of them and no other)
WRONG = {
    "wrong_homography_ignores_ids.py": (ALL_H, {"homographies_ignoring_ids"}),
    "wrong_scale_only_when_normalized.py": ({PLAIN_H}, {"scaled", "h22_not_one"}),
    "wrong_homography_cv2_findhomography.py": ({NOISY_H, PLAIN_H}, {"homographies_by_cv2_findhomography"}),
    "wrong_homography_pixels_to_board.py": (ALL_H, {"homographies_pixels_to_board", "inverse"}),
    "wrong_denormalization_backwards.py": (ALL_H - {PLAIN_H}, {"normalization_undone_backwards"}),
    "wrong_intrinsics_without_unit_norm.py": ({NOISY_K, ZERO_SKEW_K}, {"intrinsics_without_unit_norm"}),
    "wrong_zero_skew_by_dropping_gamma.py": ({ZERO_SKEW_K}, {"zero_skew_by_dropping_gamma"}),
    "wrong_unnormalized_dlt.py": ({NOISY_H}, {"unnormalized_dlt"}),
    "wrong_transposed_homography.py": (ALL_H, {"transposed", "homographies_reshaped_by_columns"}),
    "wrong_skew_dropped.py": ({NOISY_K}, {"skew_dropped"}),
}
CORRECT = ["solution.py", "correct_eigh_and_cholesky.py", "correct_grouped_by_sorting.py"]


@pytest.fixture(scope="module")
def report(calibration_lesson):
    return graded_once(calibration_lesson, "calibration", SEED)


@pytest.mark.parametrize("name", CORRECT)
def test_correct_solutions_score_full_marks_on_several_seeds(calibration_lesson, name):
    for seed in SEEDS:
        started = time.perf_counter()
        graded = grade(calibration_lesson, submission("calibration", name), seed=seed)
        seconds = time.perf_counter() - started
        print(f"\ngrading {name} (seed {seed}) took {seconds:.1f} s")
        assert graded.score == 20.0, (seed, failed(graded))
        assert not graded.practice and len(graded.seeds["clean"]) == 2


@pytest.mark.parametrize("name", sorted(WRONG))
def test_a_wrong_implementation_loses_its_checks_with_a_hint_naming_the_cause(report, name):
    checks, causes = WRONG[name]
    graded = report(name)
    lost = {t.name: t for t in graded.tests if t.status == "failed"}
    assert set(lost) == checks
    for test in lost.values():
        assert test.hints and set(test.hints) <= causes, (test.name, test.hints)
        assert "Not graded" not in test.output


def test_ignoring_ids_fails_on_the_partial_shuffled_variant_only(report):
    clean = next(t for t in report("wrong_homography_ignores_ids.py").tests if t.name == CLEAN_H)
    assert clean.output.startswith(f"Check: {CLEAN_H.removeprefix(HOMOGRAPHY)}\n"
                                   "Failed on 1 of the 2 variants of the data (variant 2).\n"
                                   "Variant 2: 8 synthetic photos")
    assert "partial boards" in clean.output and "random order" in clean.output
    assert "Hint: your homographies pair the k-th corner of a view with board corner k" in clean.output
    assert "board_points[corners.ids[k], :2] [homographies_ignoring_ids]" in clean.output


def test_a_result_right_only_up_to_scale_is_told_so_on_the_normalize_false_check(report):
    (output,) = failed(report("wrong_scale_only_when_normalized.py")).values()
    assert "Controls of estimate_homographies: normalize=False" in output
    hints = hint_lines(output)
    assert any("right up to a scale factor" in line and line.endswith("[scaled]") for line in hints)
    assert any("entry [2, 2] of your result" in line and line.endswith("[h22_not_one]") for line in hints)


def test_opencv_find_homography_is_named_and_explained(report):
    lost = failed(report("wrong_homography_cv2_findhomography.py"))
    assert "Hint: your homographies are cv2.findHomography's: it refines the DLT by Levenberg-Marquardt" \
        in lost[NOISY_H]


def test_the_unnormalized_dlt_is_told_what_to_fix(report):
    (output,) = failed(report("wrong_unnormalized_dlt.py")).values()
    assert output.startswith("Check: noisy data: the normalized DLT's homographies, up to scale\n"
                             "Data: 8 synthetic")
    assert "relative difference after the best scale factor" in output and "allowed 0.0001" in output
    assert "Hint: your homographies are what the DLT gives without normalization" in output
    assert "mean distance is sqrt(2)" in output


def test_the_transposed_homography_is_recognised(report):
    lost = failed(report("wrong_transposed_homography.py"))
    assert "Hint: your matrix is the expected one transposed" in lost[PLAIN_H]
    poses = lost[POSES_H]
    assert "metric rotation_error_max_deg after running the pipeline to estimate_extrinsics" in poses
    assert "needed at most 0.5 (the reference gets" in poses


def test_the_dropped_skew_is_recognised(report):
    (output,) = failed(report("wrong_skew_dropped.py")).values()
    assert "at index [0, 1]" in output
    assert "Expected:\n[[" in output and "Got:\n[[" in output
    assert "Hint: your skew K[0, 1] is exactly 0 but zero_skew is false" in output


# --- the data: partial boards in random order ------------------------------------------------------
PARTIAL = {"num_views": 4, "noise_px": 0.0, "pose_spread_deg": 25.0, "missing_corners": 0.4,
           "shuffle_corners": True}


def test_partial_boards_keep_ids_and_the_photos_of_the_seed():
    partial = open_session(PIPELINE, "synthetic", {**PARTIAL, "seed": 5}, seed=5)
    whole = open_session(PIPELINE, "synthetic", {"num_views": 4, "noise_px": 0.0, "pose_spread_deg": 25.0,
                                                 "seed": 5}, seed=5)
    corners, exact = partial.state["corners"], partial.truth["corners"]
    counts = np.bincount(corners.view, minlength=4)
    assert np.all(counts >= 8) and np.all(counts < 54) and len(set(counts.tolist())) > 1
    assert np.any(np.diff(corners.view) != 0) and not np.all(np.diff(corners.view) >= 0)  # views interleaved
    assert np.any(np.diff(corners.ids[corners.view == 0]) < 0)  # a view's corners out of board order
    where = corners.view * 54 + corners.ids
    assert len(np.unique(where)) == len(where)
    np.testing.assert_allclose(corners.xy, exact.xy[where], atol=1e-9)  # noise_px = 0: the exact projections
    for mine, theirs in zip(partial.state["images"].images, whole.state["images"].images, strict=True):
        np.testing.assert_array_equal(mine.pixels, theirs.pixels)
    assert "corners" not in whole.state and "partial boards" in partial.description


def test_the_lab_calibrates_from_partial_shuffled_boards():
    session = open_session(PIPELINE, "synthetic", {**PARTIAL, "noise_px": 0.3, "seed": 8}, seed=8)
    plan = session.plan("refine_calibration")
    assert "detect_corners" not in plan.steps  # the dataset gave the corners
    session.run_plan(plan)
    assert session.metrics["refine_calibration"]["rms_px"] < 0.5
    assert session.metrics["refine_calibration"]["rotation_error_max_deg"] < 0.5
    assert session.metrics["refine_calibration"]["truth_rms_px"] < 0.3
    np.testing.assert_allclose(session.state["K"], session.truth["K"], rtol=0.02, atol=2.0)
    reprojected = session.state["reprojected"]
    np.testing.assert_array_equal(reprojected.view, np.sort(session.state["corners"].view))
    session.run("undistort_image", {"view": 1})
    assert session.state["undistorted"].width == 640


def test_the_reference_homographies_do_not_depend_on_the_corners_order():
    session = open_session(PIPELINE, "synthetic", {**PARTIAL, "noise_px": 1.0, "seed": 2}, seed=2)
    corners, board_points = session.state["corners"], session.state["board_points"]
    order = np.lexsort((corners.ids, corners.view))
    from lab.core import Points2D

    sorted_corners = Points2D(corners.xy[order], view=corners.view[order], ids=corners.ids[order])
    np.testing.assert_allclose(estimate_homographies(corners, board_points),
                               estimate_homographies(sorted_corners, board_points), rtol=1e-9, atol=1e-9)
