"""lessons/04-sfm beyond the generic checks of test_every_lesson.py: a student's own correct solution
scores full marks (and how long grading takes), and the messages the wrong implementations get say
what to fix.

Seeds are fixed here (``seed=``) so the tests are reproducible; graded for real, every run draws
fresh hidden seeds.
"""

from __future__ import annotations

import time

import pytest

from lab.lessons.format import load_lesson
from lab.lessons.grader import grade

from lesson_helpers import REPO, submission

SEED = 20240917


@pytest.fixture(scope="module")
def sfm_lesson():
    return load_lesson(REPO / "lessons" / "04-sfm")


def failed(report) -> dict[str, str]:
    return {t.name: t.output for t in report.tests if t.status == "failed"}


def test_the_lesson_uses_the_teaching_pipeline(sfm_lesson):
    assert sfm_lesson.module == "lab.modules.sfm_basics:PIPELINE"
    assert sfm_lesson.pipeline.name == "sfm_basics"
    assert [t.step for t in sfm_lesson.tasks] == ["estimate_poses_linear", "triangulate_points_linear",
                                                  "jacobian_sparsity"]
    assert sfm_lesson.points == 30.0


def test_a_student_solution_scores_full_marks_and_grading_time_is_reported(sfm_lesson):
    started = time.perf_counter()
    report = grade(sfm_lesson, submission("sfm", "solution.py"), seed=SEED)
    seconds = time.perf_counter() - started
    print(f"\ngrading one sfm submission took {seconds:.1f} s")
    assert report.score == 30.0, failed(report)


def test_a_rotation_not_projected_onto_so3_is_told(sfm_lesson):
    report = grade(sfm_lesson, submission("sfm", "wrong_no_orthonormalization.py"), seed=SEED)
    lost = failed(report)
    rotation = lost["Linear PnP: noisy data: every R is a rotation (R^T R = I, det R = +1)"]
    assert "metric orthonormality_linear after running the pipeline to refine_poses on your poses_linear" in rotation
    assert "needed at most 1e-09" in rotation
    assert report.score == 26.0  # the refinement starts from the nearest rotation: the rest is right


def test_the_sign_taken_from_the_last_entry_puts_points_behind_cameras(sfm_lesson):
    report = grade(sfm_lesson, submission("sfm", "wrong_sign_from_last_entry.py"), seed=SEED)
    lost = failed(report)
    exact = lost["Linear PnP: exact data: the true poses [R | t]"]
    assert "Expected:\n[[" in exact and "Got:\n[[" in exact
    behind = lost["Linear PnP: noisy data: every point in front of the camera that sees it (cheirality)"]
    assert "metric points_behind_linear" in behind and "(the reference gets 0)" in behind
    assert not any(name.startswith("Linear triangulation") or name.startswith("Sparsity") for name in lost)


def test_the_unnormalized_pnp_is_recognised_on_noisy_data_only(sfm_lesson):
    report = grade(sfm_lesson, submission("sfm", "wrong_no_normalization.py"), seed=SEED)
    lost = failed(report)
    assert "Linear PnP: exact data: the true poses [R | t]" not in lost
    refined = lost["Linear PnP: noisy data: the poses refined from yours (non-linear PnP) as close to the truth as "
                   "the reference's"]
    assert "metric rotation_error_deg after running the pipeline to refine_poses" in refined
    assert "so at most" in refined


def test_two_view_triangulation_loses_only_the_noisy_comparison(sfm_lesson):
    report = grade(sfm_lesson, submission("sfm", "wrong_triangulation_two_views.py"), seed=SEED)
    (output,) = failed(report).values()
    assert output.startswith("Check: noisy data: the reference's points (DLT in pixels over every camera that sees "
                             "the point)\nData: 60 points")
    assert "Failed: points_linear: largest difference" in output


def test_a_pattern_without_point_blocks_shows_in_the_bundle(sfm_lesson):
    report = grade(sfm_lesson, submission("sfm", "wrong_sparsity_missing_points.py"), seed=SEED)
    lost = failed(report)
    prefix = "Sparsity pattern of the bundle-adjustment Jacobian: noisy data: "
    missing = lost[prefix + "no entry the Jacobian has is left out (each row: its camera's 6 columns and its "
                            "point's 3)"]
    assert "metric sparsity_missing after running the pipeline to bundle_adjust_scene on your sparsity" in missing
    assert prefix + "no entry marked that the Jacobian never has" not in lost
    bundle = lost[prefix + "bundle adjustment with your pattern, final reprojection RMS as the reference's"]
    assert "metric ba_rms_px" in bundle and "(1.001 x reference + 1e-06)" in bundle


def test_a_pattern_with_every_entry_loses_the_comparisons_but_not_the_bundle(sfm_lesson):
    """Extra entries only cost evaluations: the bundle still reaches the reference's error."""
    source = ("import numpy as np\n" + submission("sfm", "solution.py").split("def jacobian_sparsity")[0]
              + "def jacobian_sparsity(camera_indices, point_indices, num_cameras, num_points):\n"
                "    return np.ones((2 * len(camera_indices), 6 * num_cameras + 3 * num_points), dtype=bool)\n")
    report = grade(sfm_lesson, source, seed=SEED)
    prefix = "Sparsity pattern of the bundle-adjustment Jacobian: "
    assert set(failed(report)) == {prefix + "exact data: the reference's pattern, entry by entry",
                                   prefix + "noisy data: the reference's pattern, entry by entry",
                                   prefix + "noisy data: no entry marked that the Jacobian never has"}
