"""lessons/08-diffusion beyond the generic checks of test_every_lesson.py: correct solutions written
differently (float32 arithmetic included) score full marks on several assignment seeds, every wrong
implementation loses exactly the checks it should with a hint that names its cause (swapped
arguments are told "swapped", not diffusers' convention), and the lesson's steps are the samplers'
math.

The assignment seed is fixed here (``seed=``), as the server fixes one per lesson.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules.diffusion import combine_guidance, ddim_step, ddim_update

from lesson_helpers import REPO, failed, graded_once, hint_lines, submission

SEED = 20261122
SEEDS = (SEED, 5)

GUIDANCE = "Classifier-free guidance: "
DDIM = "The DDIM update: "
W2 = GUIDANCE + "guidance scale w = 2: the reference's guided noise prediction"
W0 = GUIDANCE + "guidance scale w = 0: the conditional prediction itself"
W5 = GUIDANCE + "guidance scale w = 5: the reference's guided noise prediction"
STEP = GUIDANCE + "one reference DDIM step on your guided prediction lands where the reference's does"
ETA0 = DDIM + "eta = 0 (deterministic DDIM): the reference's x_prev"
ETA1 = DDIM + "eta = 1 (DDPM's variance): the reference's x_prev with the same noise"
ETA05 = DDIM + "eta = 0.5: the reference's x_prev with the same noise"
LAST = DDIM + "the last step (abar_prev = 1): x_prev is the predicted clean sample"
SWAPPED = "swapped(eps_conditional, eps_unconditional)"

#: wrong fixture -> (the checks it loses, the hint names that may name its cause; every failed check carries
#: at least one of them and no other)
WRONG = {
    "wrong_guidance_swapped_arguments.py": ({W2, W0, W5, STEP}, {"swapped", "unconditional_prediction"}),
    "wrong_guidance_diffusers_scale.py": ({W2, W0, W5, STEP},
                                          {"guidance_in_diffusers_convention", "unconditional_prediction"}),
    "wrong_guidance_forgets_unconditional.py": ({W2, W5, STEP}, {"guidance_without_unconditional"}),
    "wrong_guidance_reversed.py": ({W2, W5, STEP}, {"guidance_reversed"}),
    "wrong_guidance_rescaled.py": ({W2, W5, STEP}, {"guidance_rescaled"}),
    "wrong_ddim_alphas_not_square_rooted.py": ({ETA0, ETA1, ETA05, LAST}, {"ddim_without_square_roots"}),
    "wrong_ddim_direction_keeps_sigma.py": ({ETA1, ETA05}, {"ddim_direction_keeps_sigma"}),
    "wrong_ddim_eta_under_square_root.py": ({ETA05}, {"ddim_eta_under_square_root"}),
    "wrong_ddim_sigma_ratio_inverted.py": ({ETA1, ETA05}, {"ddim_sigma_ratio_inverted"}),
    "wrong_ddim_renoises_with_fresh_noise.py": ({ETA0, ETA1, ETA05}, {"ddim_renoises_with_fresh_noise"}),
}
CORRECT = ["solution.py", "correct_float32.py", "correct_rearranged.py"]


@pytest.fixture(scope="module")
def diffusion_lesson():
    return load_lesson(REPO / "lessons" / "08-diffusion")


@pytest.fixture(scope="module")
def report(diffusion_lesson):
    return graded_once(diffusion_lesson, "diffusion", SEED)


def test_the_lesson_grades_guidance_and_the_ddim_update(diffusion_lesson):
    assert diffusion_lesson.module == "diffusion" and diffusion_lesson.points == 14.0
    assert [t.step for t in diffusion_lesson.tasks] == ["combine_guidance", "ddim_update"]
    assert all(d.seed is None for d in diffusion_lesson.datasets.values())  # drawn from the assignment seed


@pytest.mark.parametrize("name", CORRECT)
def test_correct_solutions_score_full_marks_on_several_seeds(diffusion_lesson, name):
    for seed in SEEDS:
        started = time.perf_counter()
        graded = grade(diffusion_lesson, submission("diffusion", name), seed=seed)
        print(f"\ngrading {name} (seed {seed}) took {time.perf_counter() - started:.1f} s")
        assert graded.score == 14.0, (seed, failed(graded))


@pytest.mark.parametrize("name", sorted(WRONG))
def test_a_wrong_implementation_loses_its_checks_with_a_hint_naming_the_cause(report, name):
    checks, causes = WRONG[name]
    graded = report(name)
    lost = {t.name: t for t in graded.tests if t.status == "failed"}
    assert set(lost) == checks
    for test in lost.values():
        assert test.hints and {base_name(h) for h in test.hints} <= causes, (test.name, test.hints)


def base_name(hint: str) -> str:
    """A generic mutant's hint name without its arguments: ``swapped(a, b)`` -> ``swapped``."""
    return hint.split("(", 1)[0]


def test_swapped_arguments_are_told_swapped_not_diffusers_convention(report):
    lost = failed(report("wrong_guidance_swapped_arguments.py"))
    for check in (W2, W5, STEP):
        (hint,) = hint_lines(lost[check])
        assert "eps_conditional and eps_unconditional swapped" in hint and "diffusers" not in hint
        assert hint.endswith(f"[{SWAPPED}]")
    # at w = 0 both mistakes give eps_u: the hint asks which
    (hint,) = hint_lines(lost[W0])
    assert "did you swap the two arguments, or use diffusers' convention" in hint
    assert hint.endswith("[unconditional_prediction]")


def test_diffusers_guidance_convention_is_recognised(report):
    graded = report("wrong_guidance_diffusers_scale.py")
    lost = failed(graded)
    assert graded.score == 8.0
    (hint,) = hint_lines(lost[W2])
    assert "Expected:" in lost[W2] and "Hint: you wrote eps_u + w (eps_c - eps_u)" in hint and "swapped" not in hint


def test_diffusers_convention_names_nothing_at_w0_where_it_equals_swapped_arguments(diffusion_lesson):
    mistake = diffusion_lesson.mistakes["guidance_in_diffusers_convention"]
    c, u = np.eye(2), np.ones((2, 2))
    np.testing.assert_allclose(mistake(c, u, guidance_scale=3.0), u + 3.0 * (c - u))
    with pytest.raises(ValueError, match="w = 0"):
        mistake(c, u, guidance_scale=0.0)


def test_forgotten_unconditional_term_passes_only_w0(report):
    lost = failed(report("wrong_guidance_forgets_unconditional.py"))
    assert W0 not in lost and len(lost) == 3
    assert "x_prev" in lost[STEP]


def test_a_float32_result_gets_full_marks_and_no_dtype_hint(report):
    """The issue's case: float32 guidance used to fail at 1e-9 with Expected and Got printed alike. The
    network's predictions are float32 numbers, so float32 arithmetic is legitimate: the checks allow 1e-5."""
    graded = report("correct_float32.py")
    assert graded.score == 14.0, failed(graded)
    assert not any("float32" in t.output or t.hints for t in graded.tests)


def test_the_lesson_steps_are_the_samplers_math():
    rng = np.random.default_rng(0)
    x, eps, z, eps_u = (rng.standard_normal((5, 4)) for _ in range(4))
    np.testing.assert_allclose(ddim_update(x, eps, np.array([0.3, 0.6]), z, eta=0.7),
                               ddim_step(x, eps, 0.3, 0.6, eta=0.7, noise=z))
    np.testing.assert_allclose(combine_guidance(eps, eps_u, guidance_scale=0.0), eps)
