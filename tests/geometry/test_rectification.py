"""lab.geometry.rectification: Bouguet's rectification against cv2.stereoRectify, pixels and maps against OpenCV."""

import cv2
import numpy as np
import pytest

from lab.core import InvalidValue
from lab.geometry.camera import project
from lab.geometry.rectification import (StereoCalibration, relative_pose, rectification_map, rectify_pixels,
                                        stereo_rectify)
from lab.geometry.rotations import rotvec_to_matrix

SIZE = (640, 480)
K1 = np.array([[510.0, 0.0, 322.0], [0.0, 505.0, 238.0], [0.0, 0.0, 1.0]])
K2 = np.array([[498.0, 0.0, 316.0], [0.0, 501.0, 244.0], [0.0, 0.0, 1.0]])
D1 = np.array([-0.08, 0.02, 0.0008, -0.0004, 0.0])
D2 = np.array([-0.06, 0.01, -0.0005, 0.0003, 0.0])
R = rotvec_to_matrix(np.array([0.02, -0.06, 0.015]))
T = np.array([-0.12, 0.006, -0.004])


def opencv(K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T, flags=cv2.CALIB_ZERO_DISPARITY):
    return cv2.stereoRectify(K1, D1, K2, D2, SIZE, R, T.reshape(3, 1), flags=flags, alpha=-1)


def test_stereo_rectify_matches_opencv():
    ours = stereo_rectify(K1, D1, K2, D2, SIZE, R, T)
    R1, R2, P1, P2, Q, _, _ = opencv()
    np.testing.assert_allclose(ours.R_left, R1, atol=1e-12)
    np.testing.assert_allclose(ours.R_right, R2, atol=1e-12)
    np.testing.assert_allclose(ours.P_left, P1, atol=1e-3)  # principal points: Newton vs 5 OpenCV iterations
    np.testing.assert_allclose(ours.P_right, P2, atol=1e-3)
    np.testing.assert_allclose(ours.Q, Q, atol=1e-3)
    assert not ours.vertical
    assert ours.baseline == pytest.approx(np.linalg.norm(T))
    assert ours.disparity_offset == pytest.approx(0.0)


def test_stereo_rectify_without_zero_disparity_matches_opencv():
    ours = stereo_rectify(K1, D1, K2, D2, SIZE, R, T, zero_disparity=False)
    _, _, P1, P2, Q, _, _ = opencv(flags=0)
    np.testing.assert_allclose(ours.P_left, P1, atol=1e-3)
    np.testing.assert_allclose(ours.P_right, P2, atol=1e-3)
    np.testing.assert_allclose(ours.Q, Q, atol=1e-3)
    assert ours.disparity_offset == pytest.approx(P2[0, 2] - P1[0, 2])


def test_vertical_rig_matches_opencv():
    T_vertical = np.array([0.004, -0.15, 0.002])
    ours = stereo_rectify(K1, D1, K2, D2, SIZE, R, T_vertical)
    R1, R2, P1, P2, _, _, _ = opencv(T=T_vertical)
    assert ours.vertical
    np.testing.assert_allclose(ours.R_left, R1, atol=1e-12)
    np.testing.assert_allclose(ours.P_right, P2, atol=1e-3)


def test_rectified_rows_agree_for_any_point():
    """Known answer: after rectification a 3D point lands on the same row in both images."""
    rect = stereo_rectify(K1, D1, K2, D2, SIZE, R, T)
    points = np.random.default_rng(0).uniform([-1.0, -0.7, 1.5], [1.0, 0.7, 6.0], size=(200, 3))
    left = rectify_pixels(project(points, K1, D1), K1, D1, rect.R_left, rect.P_left)
    right = rectify_pixels(project(points @ R.T + T, K2, D2), K2, D2, rect.R_right, rect.P_right)
    assert np.abs(left[:, 1] - right[:, 1]).max() < 1e-6
    # and the disparity is f B / Z in the rectified left frame (zero disparity at infinity)
    Z = (points @ rect.R_left.T)[:, 2]
    np.testing.assert_allclose(left[:, 0] - right[:, 0], rect.K[0, 0] * rect.baseline / Z, rtol=1e-9)


def test_rectify_pixels_matches_undistort_points():
    rect = stereo_rectify(K1, D1, K2, D2, SIZE, R, T)
    pixels = np.random.default_rng(1).uniform([0, 0], SIZE, size=(50, 2))
    expected = cv2.undistortPoints(pixels[:, None], K1, D1, R=rect.R_left, P=rect.P_left,
                                   criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))[:, 0]
    np.testing.assert_allclose(rectify_pixels(pixels, K1, D1, rect.R_left, rect.P_left), expected, atol=1e-6)


def test_rectification_map_matches_init_undistort_rectify_map():
    rect = stereo_rectify(K1, D1, K2, D2, SIZE, R, T)
    map_x, map_y = cv2.initUndistortRectifyMap(K2, D2, rect.R_right, rect.P_right, SIZE, cv2.CV_32FC1)
    ours = rectification_map(K2, D2, rect.R_right, rect.P_right, SIZE)
    assert ours.shape == (SIZE[1], SIZE[0], 2)
    np.testing.assert_allclose(ours[..., 0], map_x, atol=2e-3)
    np.testing.assert_allclose(ours[..., 1], map_y, atol=2e-3)


def test_relative_pose_of_two_cameras():
    R_a, t_a = rotvec_to_matrix(np.array([0.1, 0.2, -0.1])), np.array([0.3, -0.1, 2.0])
    R_b, t_b = rotvec_to_matrix(np.array([0.12, 0.15, -0.05])), np.array([0.2, -0.1, 2.1])
    R_ab, T_ab = relative_pose(R_a, t_a, R_b, t_b)
    X = np.array([0.4, -0.3, 1.0])
    np.testing.assert_allclose(R_ab @ (R_a @ X + t_a) + T_ab, R_b @ X + t_b, atol=1e-12)


def test_stereo_calibration_checks_and_rectified_constructor():
    calibration = StereoCalibration.rectified(K1, 0.2, disparity_offset=12.5)
    assert calibration.is_rectified()
    assert calibration.baseline == pytest.approx(0.2)
    assert calibration.K_right[0, 2] - calibration.K_left[0, 2] == pytest.approx(12.5)
    assert not StereoCalibration(K1, D1, K2, D2, R, T).is_rectified()
    with pytest.raises(InvalidValue, match="baseline is zero"):
        StereoCalibration(K1, None, K2, None, np.eye(3), np.zeros(3))
    with pytest.raises(InvalidValue, match="rotation"):
        StereoCalibration(K1, None, K2, None, 2 * np.eye(3), T)
    with pytest.raises(InvalidValue, match="K_right"):
        StereoCalibration(K1, None, np.ones((3, 3)), None, np.eye(3), T)
    with pytest.raises(InvalidValue, match="dist_left"):
        StereoCalibration(K1, [0.1, 0.2, 0.3], K2, None, np.eye(3), T)
    with pytest.raises(InvalidValue, match="baseline"):
        StereoCalibration.rectified(K1, 0.0)


def test_stereo_rectify_errors():
    with pytest.raises(InvalidValue, match="baseline is zero"):
        stereo_rectify(K1, D1, K2, D2, SIZE, R, np.zeros(3))
    with pytest.raises(InvalidValue, match="size"):
        stereo_rectify(K1, D1, K2, D2, (1, 480), R, T)
    with pytest.raises(InvalidValue, match="T"):
        stereo_rectify(K1, D1, K2, D2, SIZE, R, [1.0, 2.0])
