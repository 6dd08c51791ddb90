"""lessons/04-sfm beyond the generic checks of test_every_lesson.py: a student's own correct solution
scores full marks (and how long grading takes), and the messages the wrong implementations get say
what to fix: every check a wrong fixture fails carries the hint of its mistake (lessons/04-sfm/mistakes.py
and the hints of tasks.toml), and no other mistake's.

Seeds are fixed here (``seed=``: the assignment seed) so the tests are reproducible. Each fixture is graded
once per module at SEED (:func:`graded`); correct ones, and the new wrong ones, on two more assignment seeds.
"""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules import sfm_basics

from lesson_helpers import (REPO, SUBMISSIONS, assert_every_failure_names_its_mistake, failed, graded_once,
                            hint_lines, submission)

SEED = 20240917
WRONG = sorted(p.name for p in (SUBMISSIONS / "sfm").glob("wrong_*.py"))

NOISY_POSES = ("Linear PnP: noisy data: the reference's poses (Hartley-normalized DLT, R projected onto "
               "SO(3), t divided by the mean singular value)")
POSES_BEHIND = "Linear PnP: noisy data: every point in front of the camera that sees it (cheirality)"
POSES_REFINED = ("Linear PnP: noisy data: the poses refined from yours (non-linear PnP) as close to the "
                 "truth as the reference's")
POINTS_EXACT = "Linear triangulation: exact data: the true points"
NOISY_POINTS = ("Linear triangulation: noisy data: the reference's points (DLT in pixels over every camera "
                "that sees the point)")
SPARSITY = "Sparsity pattern of the bundle-adjustment Jacobian: "
SPARSITY_ALL = {SPARSITY + name for name in (
    "exact data: the reference's pattern, entry by entry",
    "noisy data: the reference's pattern, entry by entry",
    "noisy data: no entry the Jacobian has is left out (each row: its camera's 6 columns and its point's 3)",
    "noisy data: no entry marked that the Jacobian never has",
    "noisy data: bundle adjustment with your pattern, final reprojection RMS as the reference's")}

#: The hint (a part of its ``say`` in tasks.toml) every failed check of each wrong fixture must carry.
HINTS = {
    "wrong_no_normalization.py": "your poses are those of the DLT solved without Hartley's normalization",
    "wrong_no_orthonormalization.py": "your R is P[:, :3] / mean(S), which with noise is no rotation",
    "wrong_sign_from_last_entry.py": "the cameras with t_z < 0 come out as -[R | t]",
    "wrong_sparsity_missing_points.py": "your pattern marks each observation's 6 camera columns only",
    "wrong_sparsity_point_offset.py": "your point blocks start at column 3 p_i",
    "wrong_sparsity_u_rows_only.py": "your pattern marks only row 2 i (the u residual) of each observation",
    "wrong_triangulation_two_views.py":
        "your points are triangulated from the first two cameras that see them only",
    "wrong_triangulation_without_K.py": "your projection matrices are [R_v | t_v] without K",
    "wrong_pnp_in_pixels.py": "your poses are what the DLT gives on the pixels as they are",
    "wrong_pnp_t_over_largest_singular_value.py": "your t is P[:, 3] divided by the largest singular value",
    "wrong_triangulation_y_row_uses_x.py": "your second row of each view is x p3 - p2",
    "wrong_triangulation_p1_p2_swapped.py": "your rows pair the pixel coordinates with the wrong rows of P",
    "wrong_sparsity_u_then_v_blocks.py": "your rows put all u residuals first",
    "wrong_sparsity_points_before_cameras.py": "your columns put the points first",
}
CORRECT = ["solution.py", *sorted(p.name for p in (SUBMISSIONS / "sfm").glob("correct_*.py"))]

#: The checks each new wrong fixture loses, on every assignment seed (the mistake shows on any data).
LOSES = {
    "wrong_pnp_in_pixels.py": {"Linear PnP: exact data: the true poses [R | t]", NOISY_POSES, POSES_BEHIND,
                               POSES_REFINED},
    "wrong_pnp_t_over_largest_singular_value.py": {NOISY_POSES},
    "wrong_triangulation_y_row_uses_x.py": {POINTS_EXACT, NOISY_POINTS},
    "wrong_triangulation_p1_p2_swapped.py": {POINTS_EXACT, NOISY_POINTS},
    "wrong_sparsity_u_then_v_blocks.py": SPARSITY_ALL,
    "wrong_sparsity_points_before_cameras.py": SPARSITY_ALL,
}


@pytest.fixture(scope="module")
def sfm_lesson():
    return load_lesson(REPO / "lessons" / "04-sfm")


@pytest.fixture(scope="module")
def graded(sfm_lesson):
    """``graded(name)``: the report of fixture ``name`` under SEED, graded once per module."""
    return graded_once(sfm_lesson, "sfm", SEED)


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


def test_a_rotation_not_projected_onto_so3_is_told(graded):
    report = graded("wrong_no_orthonormalization.py")
    lost = failed(report)
    rotation = lost["Linear PnP: noisy data: every R is a rotation (R^T R = I, det R = +1)"]
    assert ("metric orthonormality_linear after running the pipeline to refine_poses on your poses_linear"
            in rotation)
    assert "needed at most 1e-09" in rotation
    assert report.score == 26.0  # the refinement starts from the nearest rotation: the rest is right


def test_the_sign_taken_from_the_last_entry_puts_points_behind_cameras(graded):
    report = graded("wrong_sign_from_last_entry.py")
    lost = failed(report)
    exact = lost["Linear PnP: exact data: the true poses [R | t]"]
    assert "Expected:\n[[" in exact and "Got:\n[[" in exact
    behind = lost["Linear PnP: noisy data: every point in front of the camera that sees it (cheirality)"]
    assert "metric points_behind_linear" in behind and "(the reference gets 0)" in behind
    assert not any(name.startswith("Linear triangulation") or name.startswith("Sparsity") for name in lost)


def test_the_unnormalized_pnp_is_recognised_on_noisy_data_only(graded):
    report = graded("wrong_no_normalization.py")
    lost = failed(report)
    assert "Linear PnP: exact data: the true poses [R | t]" not in lost
    refined = lost["Linear PnP: noisy data: the poses refined from yours (non-linear PnP) as close to the "
                   "truth as the reference's"]
    assert "metric rotation_error_deg after running the pipeline to refine_poses" in refined
    assert "so at most" in refined


def test_two_view_triangulation_loses_only_the_noisy_comparison(graded):
    report = graded("wrong_triangulation_two_views.py")
    (output,) = failed(report).values()
    assert output.startswith("Check: noisy data: the reference's points (DLT in pixels over every camera "
                             "that sees the point)\nData: 60 points")
    assert "Failed: points_linear: largest difference" in output


def test_a_pattern_without_point_blocks_shows_in_the_bundle(graded):
    report = graded("wrong_sparsity_missing_points.py")
    lost = failed(report)
    prefix = "Sparsity pattern of the bundle-adjustment Jacobian: noisy data: "
    missing = lost[prefix + "no entry the Jacobian has is left out (each row: its camera's 6 columns and its "
                            "point's 3)"]
    assert ("metric sparsity_missing after running the pipeline to bundle_adjust_scene on your sparsity"
            in missing)
    assert prefix + "no entry marked that the Jacobian never has" not in lost
    bundle = lost[prefix + "bundle adjustment with your pattern, final reprojection RMS as the reference's"]
    assert "metric ba_rms_px" in bundle and "(1.001 x reference + 1e-06)" in bundle


def test_a_pattern_with_every_entry_loses_the_comparisons_but_not_the_bundle(sfm_lesson):
    """Extra entries only cost evaluations: the bundle still reaches the reference's error."""
    source = ("import numpy as np\n" + submission("sfm", "solution.py").split("def jacobian_sparsity")[0]
              + "def jacobian_sparsity(camera_indices, point_indices, num_cameras, num_points):\n"
                "    return np.ones((2 * len(camera_indices), 6 * num_cameras + 3 * num_points),\n"
                "                   dtype=bool)\n")
    report = grade(sfm_lesson, source, seed=SEED)
    prefix = "Sparsity pattern of the bundle-adjustment Jacobian: "
    assert set(failed(report)) == {prefix + "exact data: the reference's pattern, entry by entry",
                                   prefix + "noisy data: the reference's pattern, entry by entry",
                                   prefix + "noisy data: no entry marked that the Jacobian never has"}


def test_every_wrong_fixture_has_its_hint():
    assert set(HINTS) == set(WRONG)


@pytest.mark.parametrize("name", WRONG)
def test_every_check_a_mistake_fails_says_what_to_fix(graded, name):
    """Each failed check names the mistake (same_as_mistake with lessons/04-sfm/mistakes.py), and no other."""
    assert_every_failure_names_its_mistake(graded(name), HINTS, name)


def test_the_mistakes_dlt_with_hartleys_normalization_is_the_labs(sfm_lesson):
    """The PnP mistakes change one thing of the lab's own DLT: with every step kept it gives the reference."""
    mistakes = sfm_lesson.mistakes
    state = sfm_basics.synthetic(num_points=30, num_views=4, noise_px=1.0, map_noise=0.05, seed=3).state
    inputs = (state["points3d"], state["observations"], state["K"])
    reference = sfm_basics.estimate_poses_linear(*inputs)
    rebuilt = mistakes["_poses_from"](mistakes["_dlt_matrices"](*inputs, hartley=True), project_onto_so3=True)
    np.testing.assert_allclose(rebuilt, reference, rtol=0, atol=1e-10)
    assert np.any(reference[:, 2, 3] < 0)  # a camera with the world origin behind it: the sign mistake shows
    for mistake in ("pnp_without_normalization", "pnp_without_orthonormalization",
                    "pnp_sign_from_last_entry"):
        assert np.abs(mistakes[mistake](*inputs) - reference).max() > 1e-6, mistake


def test_a_hint_compares_as_it_says_so_right_poses_times_two_get_no_sign_hint(sfm_lesson):
    """The sign mistake is +-1 times the right pose per camera, so its pipeline-stage hints compare with
    allclose (compare = "allclose" in tasks.toml), not up to scale: 2 [R | t] is not told it flipped signs."""
    source = submission("sfm", "solution.py").replace("def estimate_poses_linear(", "def _right_poses(")
    source += ("\n\ndef estimate_poses_linear(*args, **kwargs):\n"
               "    return 2.0 * _right_poses(*args, **kwargs)\n")
    lost = failed(grade(sfm_lesson, source, seed=SEED))
    assert lost and all(name.startswith("Linear PnP") for name in lost)
    assert not any(HINTS["wrong_sign_from_last_entry.py"] in output for output in lost.values())


@pytest.mark.parametrize("name", CORRECT)
@pytest.mark.parametrize("seed", [SEED, 1, 2])
def test_correct_solutions_written_differently_score_full_marks(sfm_lesson, graded, name, seed):
    """The polar decomposition for R, the eigenvectors of A^T A for the null vector, batched SVDs with zero
    rows, a float or uint8 pattern (scipy.sparse's .toarray()): the same numbers, full marks."""
    report = graded(name) if seed == SEED else grade(sfm_lesson, submission("sfm", name), seed=seed)
    assert report.score == 30.0, failed(report)


@pytest.mark.parametrize("name", sorted(LOSES))
@pytest.mark.parametrize("seed", [SEED, 5])
def test_the_new_mistakes_lose_exactly_their_checks_on_any_seed(sfm_lesson, graded, name, seed):
    report = graded(name) if seed == SEED else grade(sfm_lesson, submission("sfm", name), seed=seed)
    assert set(failed(report)) == LOSES[name]


@pytest.mark.parametrize("name", WRONG)
def test_every_failed_check_names_only_the_fixtures_cause(graded, name):
    """The hint names of each failed check (``[name]`` at the end of a hint line) are among the fixture's
    ``# cause:`` line."""
    match = re.search(r"^# cause: (.+)$", submission("sfm", name), re.M)
    assert match, f"{name} has no # cause: line"
    allowed = {cause.strip() for cause in match.group(1).split(",")}
    for check, output in failed(graded(name)).items():
        names = {line.rsplit("[", 1)[1].rstrip("]") for line in hint_lines(output) if line.endswith("]")}
        assert names and names <= allowed, f"{check}: {names} outside {allowed}"
        assert "Not graded" not in output


def test_the_new_mistakes_match_the_lessons_own_functions(sfm_lesson):
    """Each new mistake of mistakes.py differs from the reference on noisy data (so it can name a mistake) and
    the sparsity mistakes are permutations of the reference's pattern (the same entries, moved)."""
    mistakes = sfm_lesson.mistakes
    state = sfm_basics.synthetic(num_points=30, num_views=4, noise_px=1.0, map_noise=0.05, seed=3).state
    poses = sfm_basics.estimate_poses_linear(state["points3d"], state["observations"], state["K"])
    for name in ("pnp_in_pixels", "pnp_t_over_largest_singular_value"):
        got = mistakes[name](state["points3d"], state["observations"], state["K"])
        assert np.abs(got - poses).max() > 1e-6, name
    points = sfm_basics.triangulate_points_linear(state["observations"], poses, state["K"])
    for name in ("triangulation_y_row_uses_x", "triangulation_p1_p2_swapped"):
        assert np.abs(mistakes[name](state["observations"], poses, state["K"]) - points).max() > 1e-3, name
    indices = (state["camera_indices"], state["point_indices"], state["num_cameras"], state["num_points"])
    pattern = sfm_basics.jacobian_sparsity(*indices)
    for name in ("sparsity_u_then_v_blocks", "sparsity_points_before_cameras"):
        moved = mistakes[name](*indices)
        assert moved.shape == pattern.shape and moved.sum() == pattern.sum()
        assert not np.array_equal(moved, pattern)
