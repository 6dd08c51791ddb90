"""Comparisons, detectors of common mistakes, and the checks on what came back."""

from __future__ import annotations

import numpy as np
import pytest

from lab.core import Image, ImageSet, PointCloud
from lab.lessons import checks


def rotation(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(degrees)
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


H = np.array([[2.0, 0.3, 100.0], [-0.1, 1.5, 50.0], [1e-3, 2e-3, 1.0]])
STACK = np.stack([H, H * [[1, 2, 1], [1, 1, 1], [1, 1, 1]], H.T])


# --- comparisons: known answers, pass and fail, messages ------------------------------------------------
def test_allclose_passes_within_tolerance_and_names_the_worst_entry():
    assert checks.allclose(STACK, STACK + 1e-12).passed
    bad = STACK.copy()
    bad[1, 0, 2] += 0.5
    outcome = checks.allclose(bad, STACK, rtol=1e-6, atol=1e-9)
    assert not outcome.passed
    assert "index [1, 0, 2]" in outcome.summary and "(item 1)" in outcome.expected
    assert "Expected:" in outcome.message() and "Got:" in outcome.message()


def test_allclose_on_scalars():
    assert checks.allclose(np.float64(1.0), np.float64(1.0 + 1e-9), rtol=1e-6).passed
    outcome = checks.allclose(np.float64(2.0), np.float64(1.0))
    assert not outcome.passed and "got 2, expected 1" in outcome.summary


@pytest.mark.parametrize("scale", [1.0, -3.0, 1e-4, 250.0])
def test_equal_up_to_scale_accepts_any_scale_per_item(scale):
    scales = np.array([scale, 1.0, -2.0])[:, None, None]
    assert checks.equal_up_to_scale(STACK * scales, STACK, rtol=1e-9).passed


def test_equal_up_to_scale_measures_the_relative_difference():
    noisy = STACK.copy()
    noisy[2, 0, 0] *= 1.01
    outcome = checks.equal_up_to_scale(noisy, STACK, rtol=1e-4)
    assert not outcome.passed and "(item 2)" in outcome.summary
    assert checks.equal_up_to_scale(noisy, STACK, rtol=1e-2).passed


def test_equal_up_to_scale_of_zeros_fails_clearly():
    outcome = checks.equal_up_to_scale(np.zeros((3, 3)), H)
    assert not outcome.passed and "all zeros" in outcome.summary


def test_equal_up_to_scale_without_items_uses_one_scale():
    scaled = STACK * np.array([1.0, 2.0, 1.0])[:, None, None]
    assert checks.equal_up_to_scale(scaled, STACK, items=True).passed
    assert not checks.equal_up_to_scale(scaled, STACK, items=False).passed


def test_equal_up_to_sign_per_item():
    vectors = np.array([[1.0, 2.0, 3.0], [0.0, -1.0, 4.0]])[:, None, :].repeat(3, axis=1)
    flipped = vectors * np.array([1.0, -1.0])[:, None, None]
    assert checks.equal_up_to_sign(flipped, vectors).passed
    assert not checks.equal_up_to_sign(flipped * 1.1, vectors).passed


def test_rotation_angle_known_answer():
    R = rotation([0, 0, 1], 30)
    assert checks.rotation_angle(R, R).passed
    outcome = checks.rotation_angle(rotation([1, 2, 3], 2.0) @ R, R, max_deg=1.0)
    assert not outcome.passed and "2 deg" in outcome.summary
    assert checks.rotation_angle(rotation([1, 2, 3], 0.5) @ R, R, max_deg=1.0).passed


def test_relative_error_psnr_and_bad_pixels():
    assert checks.relative_error(H * 1.0005, H, max_relative=1e-3).passed
    assert not checks.relative_error(H * 1.01, H, max_relative=1e-3).passed
    image = np.linspace(0, 1, 100).reshape(10, 10)
    assert checks.psnr(image + 0.001, image, min_db=40).passed  # 60 dB
    outcome = checks.psnr(image + 0.1, image, min_db=40)
    assert not outcome.passed and "20.00 dB" in outcome.summary
    disparity = np.full((4, 4), 10.0)
    disparity[0, 0] = np.nan
    got = disparity + 0.5
    got[1, :] = 20.0
    outcome = checks.bad_pixel_rate(got, disparity, threshold=2.0, max_rate=0.1)
    assert not outcome.passed and "26.67 %" in outcome.summary  # 4 of 15 valid pixels
    assert checks.bad_pixel_rate(got, disparity, threshold=2.0, max_rate=0.3).passed


def test_bounds_and_reference_relative_bounds():
    assert checks.below(0.3, 0.2, bound=0.5).passed
    outcome = checks.below(0.7, 0.2, bound=0.5)
    assert not outcome.passed and "reference gets 0.2" in outcome.summary
    assert checks.above(31.0, 33.0, bound=30.0).passed and not checks.above(29.0, 33.0, bound=30.0).passed
    assert checks.at_most_reference(1.0005, 1.0, factor=1.001).passed
    assert not checks.at_most_reference(1.01, 1.0, factor=1.001).passed


def test_check_options_validates_names_types_and_required_options():
    assert checks.check_options("allclose", {"rtol": 1e-3, "atol": 0}) is None
    assert checks.check_options("allclose", {"rtolerance": 1})[0] == "rtolerance"
    assert "number" in checks.check_options("allclose", {"rtol": "small"})[1]
    assert "true or false" in checks.check_options("equal_up_to_scale", {"items": 1})[1]
    assert checks.check_options("below", {})[0] == "bound"


# --- detectors ----------------------------------------------------------------------------------------------
def test_transposed_and_inverse_and_negated_and_scaled():
    assert "transposed" in checks.transposed(np.swapaxes(STACK, 1, 2) * 3.0, STACK)
    assert checks.transposed(STACK, STACK) is None
    assert "inverse" in checks.inverse(np.linalg.inv(STACK), STACK)
    assert checks.inverse(STACK, STACK) is None
    assert "opposite sign" in checks.negated(-STACK, STACK)
    assert "scale factor" in checks.scaled(STACK * 2.0, STACK)
    assert checks.scaled(STACK, STACK) is None


def test_rank_above_finds_a_rank_3_fundamental_matrix():
    F = np.array([[0.0, -1.0, 2.0], [1.0, 0.0, -3.0], [-2.0, 3.0, 0.0]])  # skew-symmetric: rank 2
    assert checks.rank_above(F, F, rank=2) is None
    message = checks.rank_above(F + np.eye(3) * 0.1, F, rank=2)
    assert message.startswith("your matrix has rank 3: enforce rank 2")


def test_entry_zero_and_entry_not():
    K = np.array([[500.0, 2.0, 320.0], [0.0, 505.0, 240.0], [0.0, 0.0, 1.0]])
    no_skew = K.copy()
    no_skew[0, 1] = 0.0
    assert "exactly 0" in checks.entry_zero(no_skew, K, index=[0, 1])
    assert checks.entry_zero(K, K, index=[0, 1]) is None
    assert checks.entry_zero(no_skew, no_skew, index=[0, 1]) is None  # the expected one is 0 too
    assert "must be 1" in checks.entry_not(STACK * 2.0, STACK, index=[2, 2], value=1.0)
    assert checks.entry_not(STACK / STACK[:, 2:, 2:], STACK, index=[2, 2]) is None


def test_permuted_items():
    assert "different order" in checks.permuted(STACK[[1, 0, 2]], STACK)
    assert checks.permuted(STACK, STACK) is None
    assert checks.permuted(STACK[[1, 0, 2]] + 5.0, STACK) is None


def test_same_as_mistake_fires_only_when_the_graders_comparison_passed():
    ok, bad = checks.allclose(np.ones(3), np.ones(3)), checks.allclose(np.ones(3), np.zeros(3))
    assert ok.passed and not bad.passed
    found = checks.detect("same_as_mistake", np.ones(3), np.zeros(3), {"outcome": ok, "mistake": "argmax"})
    assert found == "your result is what the known mistake 'argmax' computes"
    assert checks.detect("same_as_mistake", np.ones(3), np.zeros(3),
                         {"outcome": bad, "mistake": "argmax"}) is None
    assert checks.detect("same_as_mistake", np.ones(3), np.zeros(3), {"mistake": "argmax"}) is None


def test_detect_tolerates_shapes_that_do_not_apply():
    assert checks.detect("transposed", np.ones(3), np.ones(3), {}) is None
    assert checks.detect("entry_zero", np.ones(3), np.ones(3), {"index": [0, 1]}) is None


# --- what came back -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("got,expected,needle", [
    ([1.0, 2.0], np.zeros(2), "np.asarray"),
    (np.zeros((3, 1)), np.zeros(3), "reshape it to (3,)"),
    (np.zeros((3, 3)), np.zeros((5, 3, 3)), "one item where 5 were expected"),
    (np.zeros((3, 2)), np.zeros((2, 3)), "rows and columns swapped"),
    (np.array([1.0, np.nan]), np.zeros(2), "1 NaN or infinite"),
    (np.array(["a", "b"]), np.zeros(2), "real numbers"),
    ("3", 3.0, "must be a number"),
    (ImageSet((Image(np.zeros((2, 2))),)), np.zeros(2), "numpy array"),
    (PointCloud(np.zeros((2, 3))), ImageSet((Image(np.zeros((2, 2))),)), "must be a ImageSet"),
])
def test_structure_problem_names_what_is_wrong(got, expected, needle):
    problem = checks.structure_problem(got, expected, what="out")
    assert problem is not None and needle in problem


def test_structure_problem_accepts_a_right_value():
    assert checks.structure_problem(np.zeros((2, 3)), np.ones((2, 3)), what="x") is None
    assert checks.structure_problem(np.zeros(3, dtype=np.int64), np.ones(3), what="x") is None
    assert checks.structure_problem(PointCloud(np.zeros((2, 3))), PointCloud(np.ones((2, 3))),
                                    what="x") is None
    problem = checks.structure_problem(PointCloud(np.zeros((3, 3))), PointCloud(np.ones((2, 3))), what="c")
    assert "has shape (3, 3)" in problem


def test_as_compared_and_select():
    images = ImageSet((Image(np.zeros((2, 2))), Image(np.ones((2, 2)))))
    assert checks.as_compared(images).shape == (2, 2, 2)
    cloud = PointCloud(np.ones((4, 3)))
    assert checks.select(cloud, ["xyz"], what="cloud").shape == (4, 3)
    with pytest.raises(KeyError, match="no field 'uv'"):
        checks.select(cloud, ["uv"], what="cloud")
