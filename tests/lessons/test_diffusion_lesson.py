"""lessons/08-diffusion beyond the generic checks of test_every_lesson.py: a student's own correct solution
scores full marks and the wrong guidance conventions get a message that says what to fix (the reference's
full marks, the starter's zero and each wrong variant's exact lost checks: test_every_lesson.py).

Seeds are fixed here (``seed=``) so the tests are reproducible; graded for real, the digits split and the
model's training get a fresh hidden seed at every run.
"""

from __future__ import annotations

import numpy as np
import pytest

from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules.diffusion import combine_guidance, ddim_step, ddim_update

from lesson_helpers import REPO, submission

SEED = 20261122

GUIDANCE = "Classifier-free guidance"
DDIM = "The DDIM update"


@pytest.fixture(scope="module")
def diffusion_lesson():
    return load_lesson(REPO / "lessons" / "08-diffusion")


def failed(report) -> dict[str, str]:
    return {t.name: t.output for t in report.tests if t.status == "failed"}


def test_the_lesson_grades_guidance_and_the_ddim_update(diffusion_lesson):
    assert diffusion_lesson.module == "diffusion" and diffusion_lesson.points == 14.0
    assert [t.step for t in diffusion_lesson.tasks] == ["combine_guidance", "ddim_update"]
    assert all(d.seed == "fresh" for d in diffusion_lesson.datasets.values())


def test_a_student_solution_scores_full_marks(diffusion_lesson):
    # the reference's full marks, the starter's zero and the exact checks every wrong variant loses are
    # tested for every lesson by test_every_lesson.py; here: a numpy solution and the hints' wording
    report = grade(diffusion_lesson, submission("diffusion", "solution.py"), seed=SEED)
    assert report.score == 14.0, failed(report)


def test_diffusers_guidance_convention_is_recognised(diffusion_lesson):
    report = grade(diffusion_lesson, submission("diffusion", "wrong_guidance_diffusers_scale.py"), seed=SEED)
    lost = failed(report)
    assert set(lost) == {t.name for t in report.tests if t.name.startswith(GUIDANCE)} and report.score == 8.0
    message = lost[f"{GUIDANCE}: guidance scale w = 2: the reference's guided noise prediction"]
    assert "Expected:" in message and "Hint: you wrote eps_u + w (eps_c - eps_u)" in message


def test_forgotten_unconditional_term_passes_only_w0(diffusion_lesson):
    report = grade(diffusion_lesson, submission("diffusion", "wrong_guidance_forgets_unconditional.py"),
                   seed=SEED)
    lost = failed(report)
    assert f"{GUIDANCE}: guidance scale w = 0: the conditional prediction itself" not in lost
    assert len(lost) == 3 and report.score == 9.0
    pipeline = lost[f"{GUIDANCE}: one reference DDIM step on your guided prediction lands where the "
                    "reference's does"]
    assert "x_prev" in pipeline


def test_the_lesson_steps_are_the_samplers_math():
    rng = np.random.default_rng(0)
    x, eps, z, eps_u = (rng.standard_normal((5, 4)) for _ in range(4))
    np.testing.assert_allclose(ddim_update(x, eps, np.array([0.3, 0.6]), z, eta=0.7),
                               ddim_step(x, eps, 0.3, 0.6, eta=0.7, noise=z))
    np.testing.assert_allclose(combine_guidance(eps, eps_u, guidance_scale=0.0), eps)
