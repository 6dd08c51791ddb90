"""lessons/06-splatting beyond the generic checks of test_every_lesson.py: correct solutions written
differently score full marks on several assignment seeds, the starter scores zero, every wrong implementation
(the five the issue names, and two more) loses exactly the checks it should on each seed with a hint that
names its cause, and the check data does what the checks lean on (the stacked opaque Gaussians end pixels
early, the sparse data never does; the mistakes of mistakes.py are the reference's arithmetic with one thing
changed).

The assignment seed is fixed here (``seed=``), as the server fixes one per lesson.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules.splatting import basics as B
from lab.modules.splatting.reference import T_MIN

from lesson_helpers import REPO, failed, graded_once, submission

SEED = 20261203
SEEDS = (SEED, 11)

SH = "The colour of degree 0: random coefficients: the reference's colours max(C0 f + 0.5, 0)"
COV = "The covariance in the image: random Gaussians: the reference's Sigma' = J W Sigma W^T J^T + 0.3 I"
COV_IMAGE = ("The covariance in the image: random Gaussians: the image rendered with your covariances is the "
             "reference's")
SPARSE = "Front-to-back compositing: no opaque Gaussians: the reference's pixel colours"
STACK = ("Front-to-back compositing: opaque Gaussians stacked at the centre: the reference's pixel colours, "
         "those pixels done before T < 1e-4")

#: wrong fixture -> (the checks it loses on every seed, the hints that name its cause)
WRONG = {
    "wrong_cov_without_jacobian.py": ({COV, COV_IMAGE}, {"cov_without_jacobian"}),
    "wrong_cov_rotation_transposed.py": ({COV, COV_IMAGE}, {"cov_rotation_transposed"}),
    "wrong_cov_without_dilation.py": ({COV, COV_IMAGE}, {"cov_without_dilation"}),
    "wrong_composite_back_to_front.py": ({SPARSE, STACK}, {"composite_back_to_front_weights"}),
    "wrong_composite_T_updated_first.py": ({SPARSE, STACK}, {"composite_transmittance_updated_first"}),
    "wrong_composite_no_early_termination.py": ({STACK}, {"composite_without_early_termination"}),
    "wrong_sh_clamped_at_one.py": ({SH}, {"sh_clamped_at_one"}),
}
CORRECT = ["solution.py", "correct_vectorized.py"]


@pytest.fixture(scope="module")
def splat_lesson():
    return load_lesson(REPO / "lessons" / "06-splatting")


@pytest.fixture(scope="module")
def report(splat_lesson):
    return graded_once(splat_lesson, "splatting", SEED)


def test_the_lesson_grades_three_steps_of_the_teaching_pipeline(splat_lesson):
    assert splat_lesson.module == "lab.modules.splatting:BASICS" and splat_lesson.points == 12.0
    assert [t.step for t in splat_lesson.tasks] == ["sh_dc_colors", "project_covariances",
                                                    "composite_front_to_back"]
    assert [t.points for t in splat_lesson.tasks] == [3.0, 5.0, 4.0]     # as lesson.md says
    assert all(d.seed is None for d in splat_lesson.datasets.values())  # drawn from the assignment seed


def test_the_reference_scores_full_marks_and_the_starter_zero(splat_lesson):
    assert grade(splat_lesson, reference=True, seed=SEED).score == 12.0
    starter = grade(splat_lesson, splat_lesson.starter, seed=SEED)
    assert starter.score == 0.0 and all("NotImplementedError" in t.output for t in starter.tests)


@pytest.mark.parametrize("name", CORRECT)
def test_correct_solutions_score_full_marks_on_several_seeds(splat_lesson, name):
    for seed in SEEDS:
        started = time.perf_counter()
        graded = grade(splat_lesson, submission("splatting", name), seed=seed)
        print(f"\ngrading {name} (seed {seed}) took {time.perf_counter() - started:.1f} s")
        assert graded.score == 12.0, (seed, failed(graded))


@pytest.mark.parametrize("name", sorted(WRONG))
def test_a_wrong_implementation_loses_its_checks_with_a_hint_naming_the_cause(report, splat_lesson, name):
    checks, causes = WRONG[name]
    for graded in (report(name), grade(splat_lesson, submission("splatting", name), seed=SEEDS[1])):
        lost = {t.name: t for t in graded.tests if t.status == "failed"}
        assert set(lost) == checks
        assert graded.score == 12.0 - sum(t.max_score for t in lost.values())
        for test in lost.values():
            assert test.hints and set(test.hints) <= causes, (test.name, test.hints)
            assert "\nHint: " in test.output


def _pixels(state: dict) -> B.PixelAlphas:
    s = state
    cov = B.project_covariances(s["means"], s["log_scales"], s["quats"], s["R"], s["t"], s["K"])
    return B.pixel_alphas(s["means"], cov, s["opacities"], B.sh_dc_colors(s["sh_dc"]), s["R"], s["t"], s["K"],
                          s["width"], s["height"])


@pytest.mark.parametrize("seed", range(12))
def test_the_stack_ends_pixels_early_and_the_sparse_data_never_does(seed):
    stacked = np.prod(1.0 - _pixels(B.gaussians_in_view(seed=seed).state).alphas, axis=1)
    assert np.sum(stacked < T_MIN) >= 4                 # pixels that the early termination changes
    sparse = np.prod(1.0 - _pixels(B.gaussians_in_view(opaque=0, seed=seed).state).alphas, axis=1)
    assert sparse.min() > 100 * T_MIN


def test_the_mistakes_are_the_reference_with_one_thing_changed(splat_lesson):
    mistakes = splat_lesson.mistakes
    s = B.gaussians_in_view(seed=5).state
    args = (s["means"], s["log_scales"], s["quats"], s["R"], s["t"], s["K"])
    reference = B.project_covariances(*args)
    np.testing.assert_allclose(mistakes["cov_without_dilation"](*args) + 0.3 * np.eye(2), reference,
                               rtol=1e-12)
    # unit quaternions: normalizing changes nothing, so the unnormalized formula is the reference
    unit = s["quats"] / np.linalg.norm(s["quats"], axis=1, keepdims=True)
    unit_args = (*args[:2], unit, *args[3:])
    np.testing.assert_allclose(mistakes["cov_quaternion_not_normalized"](*unit_args),
                               B.project_covariances(*unit_args), rtol=1e-10)
    # the Jacobian's depth column vanishes on the optical axis
    axis = np.array([[0.0, 0.0, 4.0]]) @ s["R"] - s["t"] @ s["R"]     # camera-frame (0, 0, 4)
    axis_args = (axis, s["log_scales"][:1], s["quats"][:1], s["R"], s["t"], s["K"])
    np.testing.assert_allclose(mistakes["cov_jacobian_without_depth_column"](*axis_args),
                               B.project_covariances(*axis_args), rtol=1e-10, atol=1e-12)
    px = _pixels(s)
    image = B.composite_front_to_back(px.alphas, px.pixel_colors, s["background"])
    no_background = mistakes["composite_without_background"](px.alphas, px.pixel_colors, s["background"])
    assert np.all(image - no_background >= 0) and np.any(image - no_background > 0.5)
    # one Gaussian per pixel: front to back and back to front agree
    one = px.alphas.copy()
    one[:, 1:] = 0.0
    over = mistakes["composite_back_to_front_weights"](one, px.pixel_colors, s["background"])
    np.testing.assert_allclose(over, B.composite_front_to_back(one, px.pixel_colors, s["background"]),
                               rtol=1e-12)
