"""lessons/02-epipolar beyond the generic checks of test_every_lesson.py: a student's own correct solution
scores full marks (and how long grading takes), the starter scores zero, and the messages the wrong
implementations get say what to fix.

Seeds are fixed here (``seed=``) so the tests are reproducible; graded for real, every dataset gets
a fresh hidden seed at every run.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from lab.data.two_view import correspondences
from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules.epipolar import PIPELINE, CANDIDATE_NAMES, decompose_essential, eight_point, recover_pose

from lesson_helpers import REPO, SUBMISSIONS, submission

SEED = 20261122

EIGHT = "Normalized 8-point algorithm"
FOUR = "The four poses of E"
CHEIRALITY = "The cheirality test"


@pytest.fixture(scope="module")
def epipolar_lesson():
    return load_lesson(REPO / "lessons" / "02-epipolar")


def failed(report) -> dict[str, str]:
    return {t.name: t.output for t in report.tests if t.status == "failed"}


def test_the_lesson_grades_the_8point_algorithm_the_decomposition_and_the_cheirality_test(epipolar_lesson):
    assert epipolar_lesson.module == "epipolar" and epipolar_lesson.points == 20.0
    assert [t.step for t in epipolar_lesson.tasks] == ["estimate_fundamental_8point", "decompose_essential",
                                                       "recover_pose"]
    assert {d.dataset for d in epipolar_lesson.datasets.values()} == {"correspondences"}
    assert all(d.seed == "fresh" for d in epipolar_lesson.datasets.values())
    stages = {c.stage for t in epipolar_lesson.tasks[1:] for c in t.checks}
    assert stages == {"output", "pipeline"}  # the pose tasks are checked through the rest of the pipeline too


def test_reference_full_marks_and_starter_zero(epipolar_lesson):
    assert grade(epipolar_lesson, reference=True, seed=SEED).score == 20.0
    starter = grade(epipolar_lesson, epipolar_lesson.starter, seed=SEED)
    assert starter.score == 0.0
    assert all("NotImplementedError" in t.output for t in starter.tests)


def test_a_student_solution_scores_full_marks_and_grading_time_is_reported(epipolar_lesson):
    started = time.perf_counter()
    report = grade(epipolar_lesson, submission("epipolar", "solution.py"), seed=SEED)
    seconds = time.perf_counter() - started
    print(f"\ngrading one epipolar submission took {seconds:.1f} s")
    assert report.score == 20.0, failed(report)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_full_marks_and_the_right_losses_on_other_hidden_seeds(epipolar_lesson, seed):
    """Fresh seeds change the data: the solution keeps full marks and each mistake loses the same points."""
    scores = {name: grade(epipolar_lesson, submission("epipolar", name), seed=seed).score
              for name in ("solution.py", "wrong_no_normalization.py", "wrong_no_rank2.py",
                           "wrong_cheirality_sign.py")}
    assert scores == {"solution.py": 20.0, "wrong_no_normalization.py": 16.0, "wrong_no_rank2.py": 16.0,
                      "wrong_cheirality_sign.py": 15.0}


def test_the_missing_normalization_is_told_what_to_fix(epipolar_lesson):
    report = grade(epipolar_lesson, submission("epipolar", "wrong_no_normalization.py"), seed=SEED)
    (output,) = failed(report).values()
    assert output.startswith("Check: noisy data: the normalized 8-point's F, rank 2, up to scale\n"
                             "Data: 300 random")
    assert "relative difference after the best scale factor" in output and "allowed 1e-07" in output
    assert "Hint: your F is what the 8-point algorithm gives without normalization" in output
    assert "mean distance from it is sqrt(2)" in output and "rank 3" not in output


def test_the_missing_rank2_step_is_recognised(epipolar_lesson):
    report = grade(epipolar_lesson, submission("epipolar", "wrong_no_rank2.py"), seed=SEED)
    (output,) = failed(report).values()
    assert "Hint: your F has rank 3: enforce rank 2" in output
    assert "without normalization" not in output


def test_the_reversed_cheirality_sign_is_recognised(epipolar_lesson):
    report = grade(epipolar_lesson, submission("epipolar", "wrong_cheirality_sign.py"), seed=SEED)
    lost = failed(report)
    assert set(lost) == {f"{CHEIRALITY}: exact data: the reference's pose",
                         f"{CHEIRALITY}: data with wrong matches: the reference's pose (counting RANSAC's "
                         "inliers only)",
                         f"{CHEIRALITY}: data with wrong matches: the direction of t refined from your pose, "
                         "as accurate as the reference's"}
    for output in lost.values():
        assert "Hint: your pose is the candidate (R" in output and "reversed" in output
        assert "positive depth" in output or "depth is positive" in output
    refined = lost[f"{CHEIRALITY}: data with wrong matches: the direction of t refined from your pose, as "
                   "accurate as the reference's"]
    assert ("metric translation_direction_error_deg after running the pipeline to refine_pose on your pose"
            in refined)
    assert "got 179." in refined or "got 180" in refined


def test_t_from_the_wrong_null_vector_is_caught_through_the_pipeline(epipolar_lesson):
    report = grade(epipolar_lesson, submission("epipolar", "wrong_translation_from_v.py"), seed=SEED)
    lost = failed(report)
    assert set(lost) == {f"{FOUR}: exact data: the reference's four candidates, in order",
                         f"{FOUR}: data with wrong matches: your candidates, then the lab's cheirality test: "
                         "the direction of t as accurate as the reference's"}
    pipeline = lost[f"{FOUR}: data with wrong matches: your candidates, then the lab's cheirality test: the "
                    "direction of t as accurate as the reference's"]
    assert "after running the pipeline to recover_pose on your candidates" in pipeline


def test_candidates_in_another_order_get_the_order_hint(epipolar_lesson):
    source = submission("epipolar", "solution.py").replace(
        "    return np.array([np.column_stack([R1, t]), np.column_stack([R2, t]),\n"
        "                     np.column_stack([R1, -t]), np.column_stack([R2, -t])])",
        "    return np.array([np.column_stack([R1, -t]), np.column_stack([R2, -t]),\n"
        "                     np.column_stack([R1, t]), np.column_stack([R2, t])])")
    assert source != submission("epipolar", "solution.py")
    report = grade(epipolar_lesson, source, seed=SEED)
    (output,) = failed(report).values()  # the lab's cheirality test does not mind the order
    assert "Hint: your four candidates are the right ones in a different order" in output


def test_the_lessons_conventions_are_the_modules():
    """What lesson.md and starter.py promise, checked on the module: unit-norm rank-2 F with
    x2^T F x1 = 0, the candidates in cv2's order, the pose one of them unchanged, names of the control."""
    data = correspondences(num_points=40, noise_px=0.0, outlier_rate=0.0, seed=9)
    x1, x2, K = data.state["x1"], data.state["x2"], data.state["K1"]
    F = eight_point(x1, x2)
    assert np.linalg.norm(F) == pytest.approx(1.0) and np.linalg.matrix_rank(F, tol=1e-9) == 2
    h1, h2 = np.column_stack([x1, np.ones(40)]), np.column_stack([x2, np.ones(40)])
    np.testing.assert_allclose(np.sum(h2 * (h1 @ F.T), axis=1), 0.0, atol=1e-9)
    candidates = decompose_essential(data.truth["E"])
    U = np.linalg.svd(data.truth["E"])[0]
    U = -U if np.linalg.det(U) < 0 else U
    np.testing.assert_allclose(candidates[0, :, 3], U[:, 2])
    np.testing.assert_allclose(candidates[2], np.column_stack([candidates[0, :, :3], -U[:, 2]]))
    pose = recover_pose(candidates, x1, x2, K, K)
    assert any(np.array_equal(pose, c) for c in candidates)
    assert PIPELINE.step("recover_pose").controls[0].name == "candidate"
    assert CANDIDATE_NAMES == ("R1 t", "R2 t", "R1 -t", "R2 -t")
    assert sorted(p.name for p in (SUBMISSIONS / "epipolar").glob("wrong_*.py")) == [
        "wrong_cheirality_sign.py", "wrong_no_normalization.py", "wrong_no_rank2.py",
        "wrong_translation_from_v.py"]
