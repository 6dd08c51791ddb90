"""lab.geometry.triangulation: DLT triangulation (against cv2.triangulatePoints), depths, the point refinement."""

import cv2
import numpy as np
import pytest

from lab.core import InvalidValue
from lab.geometry.rotations import look_at
from lab.geometry.triangulation import (point_depths, projection_matrix, refine_points, reprojection_residuals,
                                        triangulate_dlt)

K = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])


def _scene(views: int = 2, count: int = 50, seed: int = 0):
    rng = np.random.default_rng(seed)
    points = rng.uniform([-1, -1, 4], [1, 1, 7], (count, 3))
    eyes = np.array([[0.4 * v, 0.05 * v, 0.0] for v in range(views)])
    R, t = look_at(eyes, np.broadcast_to([0.0, 0.0, 5.5], eyes.shape), up=(0.0, -1.0, 0.0))
    P = projection_matrix(np.broadcast_to(K, (views, 3, 3)), R, t)
    projected = np.einsum("vij,nj->vni", P[:, :, :3], points) + P[:, None, :, 3]
    return P, points, projected[..., :2] / projected[..., 2:]


def test_projection_matrix_known_answer():
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t = np.array([1.0, 2.0, 3.0])
    P = projection_matrix(K, R, t)
    assert P.shape == (3, 4)
    np.testing.assert_allclose(P, K @ np.column_stack([R, t]))
    assert projection_matrix(np.stack([K, K]), np.stack([R, R]), np.stack([t, t])).shape == (2, 3, 4)


@pytest.mark.parametrize("views", [2, 3, 5])
def test_dlt_recovers_exact_points(views):
    P, points, x = _scene(views)
    X = triangulate_dlt(P, x)
    assert X.shape == points.shape
    np.testing.assert_allclose(X, points, atol=1e-8)


def test_dlt_matches_cv2_triangulate_points_on_noisy_pixels():
    P, points, x = _scene(2, 200, seed=3)
    noisy = x + np.random.default_rng(4).normal(0, 1.0, x.shape)
    ours = triangulate_dlt(P, noisy)
    homogeneous = cv2.triangulatePoints(P[0], P[1], noisy[0].T, noisy[1].T)
    theirs = (homogeneous[:3] / homogeneous[3]).T
    np.testing.assert_allclose(ours, theirs, rtol=1e-6, atol=1e-9)


def test_dlt_is_invariant_to_the_scale_of_each_projection():
    P, points, x = _scene(3)
    scaled = P * np.array([2.0, -0.5, 7.0])[:, None, None]
    np.testing.assert_allclose(triangulate_dlt(scaled, x), points, atol=1e-8)


def test_dlt_mask_ignores_views_that_do_not_see_a_point():
    P, points, x = _scene(3)
    garbage = x.copy()
    garbage[2, :10] = 1e4  # view 2 does not see the first 10 points
    mask = np.ones(x.shape[:2], dtype=bool)
    mask[2, :10] = False
    np.testing.assert_allclose(triangulate_dlt(P, garbage, mask), points, atol=1e-8)


def test_triangulation_errors():
    P, points, x = _scene(2)
    with pytest.raises(InvalidValue, match="projection"):
        triangulate_dlt(P[:1], x[:1])
    with pytest.raises(InvalidValue, match="points2d"):
        triangulate_dlt(P, x[0])
    with pytest.raises(InvalidValue, match="NaN"):
        triangulate_dlt(np.where(np.eye(3, 4, dtype=bool), np.nan, P), x)
    with pytest.raises(InvalidValue, match="two views"):
        triangulate_dlt(P, x, np.zeros(x.shape[:2], dtype=bool))


def test_point_depths_sign_and_value():
    P, points, _ = _scene(2)
    depth = point_depths(P, points)
    assert depth.shape == (2, len(points))
    np.testing.assert_allclose(depth[0], points[:, 2])  # camera 0 ... looks along +z from the origin
    assert np.all(depth > 0)
    assert np.all(point_depths(-P, points) > 0)  # the sign of P does not matter
    behind = points * np.array([1.0, 1.0, -1.0])
    assert np.all(point_depths(P[:1].repeat(2, 0), behind) < 0)


def test_reprojection_residuals_zero_for_exact_points():
    P, points, x = _scene(3)
    residual = reprojection_residuals(P, points, x)
    assert residual.shape == x.shape
    assert np.abs(residual).max() < 1e-9
    with pytest.raises(InvalidValue, match="points3d"):
        reprojection_residuals(P, points[:-1], x)


def test_refinement_reaches_the_exact_points_from_a_perturbed_start():
    P, points, x = _scene(2, 100, seed=7)
    start = points + np.random.default_rng(8).normal(0, 0.05, points.shape)
    refined, history = refine_points(P, x, start, iterations=20)
    np.testing.assert_allclose(refined, points, atol=1e-7)
    assert history[0] > 1.0 and history[-1] < 1e-6


def test_refinement_lowers_the_reprojection_error_of_the_dlt():
    P, points, x = _scene(2, 300, seed=9)
    noisy = x + np.random.default_rng(10).normal(0, 1.0, x.shape)
    dlt = triangulate_dlt(P, noisy)
    refined, history = refine_points(P, noisy, dlt)
    before = np.sum(reprojection_residuals(P, dlt, noisy) ** 2, axis=(0, 2))
    after = np.sum(reprojection_residuals(P, refined, noisy) ** 2, axis=(0, 2))
    assert np.all(after <= before + 1e-12)
    assert after.sum() < before.sum()
    assert np.all(np.diff(history) <= 1e-12)  # never goes up
    # two views, 4 measurements, 3 unknowns: the ML residual is about 1 px^2 per point (chi^2 with 1 dof)
    assert 0.7 < np.mean(after) < 1.3


def test_refinement_with_zero_iterations_keeps_the_points():
    P, points, x = _scene(2)
    start = points + 0.01
    refined, history = refine_points(P, x, start, iterations=0)
    np.testing.assert_array_equal(refined, start)
    assert len(history) == 1


def test_two_view_refinement_reaches_the_optimal_correction_of_cv2_correct_matches():
    """With two views the minimum of the reprojection error is Hartley and Sturm's optimal triangulation:
    ``cv2.correctMatches`` moves each pair onto the epipolar constraint, and the DLT of the corrected pair
    is the point that refine_points converges to."""
    from lab.geometry.rotations import skew

    P, points, x = _scene(2, 100, seed=11)
    noisy = x + np.random.default_rng(12).normal(0, 1.0, x.shape)
    R = np.linalg.solve(K, P[1, :, :3])
    t = np.linalg.solve(K, P[1, :, 3])
    F = np.linalg.inv(K).T @ skew(t) @ R @ np.linalg.inv(K)
    corrected1, corrected2 = cv2.correctMatches(F, noisy[0][None], noisy[1][None])
    optimal = triangulate_dlt(P, np.stack([corrected1[0], corrected2[0]]))
    refined, _ = refine_points(P, noisy, triangulate_dlt(P, noisy), iterations=30)
    np.testing.assert_allclose(refined, optimal, rtol=1e-6, atol=1e-6)  # micrometres on a 5 m scene
