"""lessons/05-nerf beyond the generic checks of test_every_lesson.py: correct solutions written differently
score full marks on several assignment seeds, every wrong implementation loses exactly the checks it should
on each of them with a hint that names its cause, and the teaching pipeline's steps are the NeRF module's
math (the closed forms the checks lean on hold for the reference itself).

The assignment seed is fixed here (``seed=``), as the server fixes one per lesson.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules.nerf import basics as B
from lab.modules.nerf import camera_rays, pixel_centres, positional_encoding, sample_pdf

from lesson_helpers import REPO, failed, graded_once, submission

SEED = 20261202
SEEDS = (SEED, 11)

ENC6 = "Positional encoding: random points, L = 6: the reference's gamma(p)"
ENC2 = "Positional encoding: random points, L = 2: the reference's gamma(p)"
DIR = "Ray directions: random cameras: the reference's directions R^T K^-1 (u, v, 1), row by row"
PROJ = "Ray directions: random cameras: the points at depth 2.5 on your rays project onto their own pixel centres"
W = "Volume-rendering weights: random densities: the reference's weights T_i alpha_i"
SLAB = "Volume-rendering weights: homogeneous slab: the opacity sum w_i is 1 - exp(-sigma (far - t_1))"
STEP = ("Volume-rendering weights: one opaque sample per ray: the expected depth sum w_i t_i is that sample's "
        "depth")
PDF = "Inverse-CDF sampling: random weights: the reference's samples"
SHARES = ("Inverse-CDF sampling: evenly spaced uniforms: the share of samples in each bin is its probability "
          "(within 1 / 64)")

#: wrong fixture -> (the checks it loses on every seed, the hints that name its cause)
WRONG = {
    "wrong_encoding_without_pi.py": ({ENC6, ENC2}, {"encoding_without_pi"}),
    "wrong_encoding_sines_then_cosines.py": ({ENC6, ENC2}, {"encoding_sines_then_cosines"}),
    "wrong_directions_camera_frame.py": ({DIR, PROJ}, {"directions_in_camera_frame"}),
    "wrong_directions_rotated_by_R.py": ({DIR, PROJ}, {"directions_rotated_by_R"}),
    "wrong_directions_half_pixel.py": ({DIR, PROJ}, {"directions_half_pixel"}),
    "wrong_weights_inclusive_cumprod.py": ({W, SLAB, STEP}, {"weights_inclusive_transmittance",
                                                              "weights_inclusive_transmittance_allclose"}),
    "wrong_weights_alpha_without_delta.py": ({W, SLAB}, {"weights_alpha_without_delta"}),
    "wrong_weights_last_interval_1e10.py": ({W, SLAB}, {"weights_last_interval_infinite"}),
    "wrong_pdf_unnormalized.py": ({PDF, SHARES}, {"pdf_unnormalized"}),
    "wrong_pdf_left_edges.py": ({PDF}, {"pdf_left_edges"}),
}
CORRECT = ["solution.py", "correct_vectorized.py"]


@pytest.fixture(scope="module")
def nerf_lesson():
    return load_lesson(REPO / "lessons" / "05-nerf")


@pytest.fixture(scope="module")
def report(nerf_lesson):
    return graded_once(nerf_lesson, "nerf", SEED)


def test_the_lesson_grades_four_steps_of_the_teaching_pipeline(nerf_lesson):
    assert nerf_lesson.module == "lab.modules.nerf.basics:PIPELINE" and nerf_lesson.points == 20.0
    assert [t.step for t in nerf_lesson.tasks] == ["positional_encoding", "ray_directions", "volume_weights",
                                                   "sample_pdf"]
    assert all(d.seed is None for d in nerf_lesson.datasets.values())  # drawn from the assignment seed


@pytest.mark.parametrize("name", CORRECT)
def test_correct_solutions_score_full_marks_on_several_seeds(nerf_lesson, name):
    for seed in SEEDS:
        started = time.perf_counter()
        graded = grade(nerf_lesson, submission("nerf", name), seed=seed)
        print(f"\ngrading {name} (seed {seed}) took {time.perf_counter() - started:.1f} s")
        assert graded.score == 20.0, (seed, failed(graded))


@pytest.mark.parametrize("name", sorted(WRONG))
def test_a_wrong_implementation_loses_its_checks_with_a_hint_naming_the_cause(report, nerf_lesson, name):
    checks, causes = WRONG[name]
    for graded in (report(name), grade(nerf_lesson, submission("nerf", name), seed=SEEDS[1])):
        lost = {t.name: t for t in graded.tests if t.status == "failed"}
        assert set(lost) == checks
        for test in lost.values():
            assert test.hints and set(test.hints) <= causes, (test.name, test.hints)
            assert "\nHint: " in test.output


def _data(**options):
    return B.synthetic(**options, seed=3)


def test_the_steps_are_the_nerf_modules_math():
    loaded = _data()
    s = loaded.state
    np.testing.assert_allclose(B.positional_encoding(s["points"], frequencies=3),
                               positional_encoding(torch.as_tensor(s["points"]), 3, include_input=False).numpy())
    gamma = B.positional_encoding(np.array([[0.25]]), frequencies=2)
    np.testing.assert_allclose(gamma, [[np.sin(np.pi / 4), np.cos(np.pi / 4), 1.0, 0.0]], atol=1e-15)
    directions = B.ray_directions(s["K"], s["R"], s["t"], s["image_size"])
    _, module_directions = camera_rays(s["K"][None], s["R"][None], s["t"][None], pixel_centres(16, 12))
    np.testing.assert_allclose(directions, module_directions[0].numpy(), rtol=1e-5, atol=1e-6)
    camera = directions @ s["R"].T
    np.testing.assert_allclose(camera[:, 2], 1.0)  # camera-frame z = 1: the ray parameter is the depth
    metrics = B.evaluate_ray_points({**s, "ray_points": B.points_along_rays(directions, s["R"], s["t"])},
                                    loaded.truth)
    assert metrics["reprojection_error_px"] < 1e-9 and metrics["ray_depth_error"] < 1e-12


def test_closed_forms_hold_for_the_reference_weights_and_samples():
    slab = _data(profile="slab")
    s = slab.state
    w = B.volume_weights(s["sigmas"], s["depths"], s["far"])
    np.testing.assert_allclose(w.sum(axis=1), slab.truth["opacity"], rtol=1e-12)
    step = _data(profile="step")
    s = step.state
    out = B.composite(B.volume_weights(s["sigmas"], s["depths"], s["far"]), s["colors"], s["depths"], s["far"])
    np.testing.assert_allclose(out.rendered_depth, step.truth["depth"], atol=1e-9)
    even = _data(evenly=True)
    s = even.state
    samples = B.sample_pdf(s["bins"], s["bin_weights"], s["uniforms"])
    np.testing.assert_allclose(samples, sample_pdf(torch.as_tensor(s["bins"]), torch.as_tensor(s["bin_weights"]),
                                                   64, deterministic=True).numpy(), atol=1e-9)
    shares = B.bin_shares(samples, s["bins"])
    assert np.max(np.abs(shares - even.truth["pdf"])) <= 1.0 / 64
