"""lab.geometry.camera: projection, OpenCV distortion and its inverse, undistortion maps, against OpenCV."""

import cv2
import numpy as np
import pytest

from lab.core import InvalidValue
from lab.geometry.camera import (as_distortion, as_intrinsics, distort, distort_with_jacobians, normalized_to_pixels,
                                 optimal_new_camera_matrix, pixels_to_normalized, project, project_points, undistort,
                                 undistort_pixels, undistortion_map)
from lab.geometry.rotations import rotvec_to_matrix

K = np.array([[520.0, 0.0, 318.0], [0.0, 515.0, 242.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.28, 0.09, 0.001, -0.0007, -0.02])
RNG = np.random.default_rng(11)
CAMERA_POINTS = RNG.uniform([-0.4, -0.3, 1.0], [0.4, 0.3, 2.0], size=(60, 3))


def test_project_matches_cv2_project_points():
    expected, _ = cv2.projectPoints(CAMERA_POINTS, np.zeros(3), np.zeros(3), K, DIST)
    np.testing.assert_allclose(project(CAMERA_POINTS, K, DIST), expected[:, 0], atol=1e-9)


def test_project_points_with_pose_matches_opencv():
    w, t = np.array([0.1, -0.2, 0.3]), np.array([0.05, -0.02, 1.5])
    X = RNG.uniform(-0.2, 0.2, size=(20, 3))
    expected, _ = cv2.projectPoints(X, w, t, K, DIST)
    np.testing.assert_allclose(project_points(X, K, DIST, rotvec_to_matrix(w), t), expected[:, 0], atol=1e-9)


def test_project_points_batches_over_views():
    R = rotvec_to_matrix(RNG.normal(scale=0.2, size=(3, 3)))
    t = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.2], [0.0, 0.1, 0.9]])
    X = RNG.uniform(-0.1, 0.1, size=(8, 3))
    batched = project_points(X[None], K, DIST, R, t)
    assert batched.shape == (3, 8, 2)
    np.testing.assert_allclose(batched[2], project_points(X, K, DIST, R[2], t[2]))


def test_pixels_and_normalized_roundtrip_with_skew():
    skewed = K.copy()
    skewed[0, 1] = 2.5
    xy = RNG.normal(scale=0.3, size=(4, 5, 2))
    np.testing.assert_allclose(pixels_to_normalized(normalized_to_pixels(xy, skewed), skewed), xy, atol=1e-14)


def test_distortion_jacobians_match_finite_differences_and_opencv():
    xy = CAMERA_POINTS[:, :2] / CAMERA_POINTS[:, 2:]
    xd, d_point, d_dist = distort_with_jacobians(xy, DIST)
    np.testing.assert_allclose(xd, distort(xy, DIST), atol=1e-15)
    eps = 1e-7
    for k in range(2):
        step = np.zeros(2)
        step[k] = eps
        numeric = (distort(xy + step, DIST) - distort(xy - step, DIST)) / (2 * eps)
        np.testing.assert_allclose(d_point[:, :, k], numeric, atol=1e-7)
    # OpenCV's projectPoints Jacobian: columns 10..14 are d(u, v)/d(dist) = diag(fx, fy) d_dist
    _, jacobian = cv2.projectPoints(CAMERA_POINTS, np.zeros(3), np.zeros(3), K, DIST)
    ours = d_dist * np.array([K[0, 0], K[1, 1]])[None, :, None]
    np.testing.assert_allclose(ours, jacobian[:, 10:15].reshape(-1, 2, 5), atol=1e-9)


def test_undistort_inverts_distort():
    xy = RNG.uniform(-0.6, 0.6, size=(200, 2))
    np.testing.assert_allclose(undistort(distort(xy, DIST), DIST), xy, atol=1e-12)
    np.testing.assert_array_equal(undistort(xy, None), xy)  # no distortion: identity


def test_undistort_pixels_matches_cv2_undistort_points():
    pixels = RNG.uniform([0, 0], [639, 479], size=(100, 2))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    expected = cv2.undistortPoints(pixels[:, None], K, DIST, R=None, P=K, criteria=criteria)[:, 0]
    np.testing.assert_allclose(undistort_pixels(pixels, K, DIST), expected, atol=1e-6)


def test_as_distortion_accepts_opencv_shapes_and_rejects_others():
    np.testing.assert_array_equal(as_distortion(None), np.zeros(5))
    np.testing.assert_array_equal(as_distortion([[0.1, 0.2, 0.0, 0.0]]), [0.1, 0.2, 0.0, 0.0, 0.0])
    with pytest.raises(InvalidValue):
        as_distortion([0.1, 0.2, 0.3])
    with pytest.raises(InvalidValue):
        as_distortion([np.nan, 0, 0, 0, 0])


def test_as_intrinsics_rejects_non_camera_matrices():
    with pytest.raises(InvalidValue):
        as_intrinsics(np.eye(4))
    with pytest.raises(InvalidValue):
        as_intrinsics(np.array([[500.0, 0, 320], [1.0, 500, 240], [0, 0, 1]]))
    with pytest.raises(InvalidValue):
        as_intrinsics(np.diag([0.0, 1.0, 1.0]))


@pytest.mark.parametrize("with_rotation", [False, True])
def test_undistortion_map_matches_init_undistort_rectify_map(with_rotation):
    R = rotvec_to_matrix(np.array([0.02, -0.01, 0.03])) if with_rotation else None
    K_new = np.array([[480.0, 0.0, 330.0], [0.0, 480.0, 235.0], [0.0, 0.0, 1.0]])
    ours = undistortion_map(K, DIST, (640, 480), K_new=K_new, R=R)
    map_x, map_y = cv2.initUndistortRectifyMap(K, DIST, np.eye(3) if R is None else R, K_new, (640, 480),
                                               cv2.CV_32FC1)
    assert ours.shape == (480, 640, 2)
    np.testing.assert_allclose(ours[..., 0], map_x, atol=2e-3)
    np.testing.assert_allclose(ours[..., 1], map_y, atol=2e-3)


@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0])
def test_optimal_new_camera_matrix_matches_opencv(alpha):
    mild = np.array([-0.1, 0.02, 0.0005, -0.0003, 0.0])  # OpenCV's 5 fixed-point iterations converge for it
    expected, _ = cv2.getOptimalNewCameraMatrix(K, mild, (640, 480), alpha)
    np.testing.assert_allclose(optimal_new_camera_matrix(K, mild, (640, 480), alpha=alpha), expected, rtol=1e-4)


def test_optimal_new_camera_matrix_close_to_opencv_under_strong_distortion():
    expected, _ = cv2.getOptimalNewCameraMatrix(K, DIST, (640, 480), 0.0)
    np.testing.assert_allclose(optimal_new_camera_matrix(K, DIST, (640, 480), alpha=0.0), expected, rtol=1e-2)


def test_optimal_new_camera_matrix_rejects_bad_alpha():
    with pytest.raises(InvalidValue):
        optimal_new_camera_matrix(K, DIST, (640, 480), alpha=1.5)
