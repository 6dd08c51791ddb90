"""lab.geometry.rotations: cross-product matrices, axis-angle, the nearest rotation, angles, SO(3) Jacobian."""

import cv2
import numpy as np
import pytest

from lab.core import InvalidValue
from lab.geometry.rotations import (look_at, matrix_to_rotvec, nearest_rotation, rotation_angle_deg, rotvec_to_matrix,
                                    skew, so3_left_jacobian)

RNG = np.random.default_rng(7)
ROTVECS = RNG.normal(size=(6, 3))


def test_skew_is_the_cross_product_batched():
    v, u = RNG.normal(size=(2, 4, 3))
    S = skew(v)
    assert S.shape == (4, 3, 3)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", S, u), np.cross(v, u), atol=1e-14)
    np.testing.assert_allclose(S, -np.swapaxes(S, 1, 2))


def test_skew_rejects_bad_shape():
    with pytest.raises(InvalidValue):
        skew(np.zeros((4, 2)))


def test_rotvec_to_matrix_matches_cv2_rodrigues():
    R = rotvec_to_matrix(ROTVECS)
    assert R.shape == (6, 3, 3)
    for w, M in zip(ROTVECS, R):
        np.testing.assert_allclose(M, cv2.Rodrigues(w)[0], atol=1e-12)


def test_rotvec_roundtrip_keeps_leading_dimensions():
    w = ROTVECS.reshape(2, 3, 3)
    w = w / np.linalg.norm(w, axis=-1, keepdims=True) * 1.3  # angles below pi: the round trip is exact
    R = rotvec_to_matrix(w)
    assert R.shape == (2, 3, 3, 3)
    np.testing.assert_allclose(matrix_to_rotvec(R), w, atol=1e-12)


def test_nearest_rotation_known_answers():
    R = rotvec_to_matrix(ROTVECS)
    np.testing.assert_allclose(nearest_rotation(R), R, atol=1e-12)  # a rotation is its own nearest
    np.testing.assert_allclose(nearest_rotation(3.0 * R), R, atol=1e-12)  # invariant to positive scale
    noisy = R + 0.05 * RNG.normal(size=R.shape)
    Q = nearest_rotation(noisy)
    np.testing.assert_allclose(Q @ np.swapaxes(Q, 1, 2), np.broadcast_to(np.eye(3), Q.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(Q), 1.0, atol=1e-12)
    # closer to the noisy matrix than the rotation we started from
    assert np.all(np.linalg.norm(Q - noisy, axis=(1, 2)) <= np.linalg.norm(R - noisy, axis=(1, 2)) + 1e-12)


def test_nearest_rotation_of_a_reflection_is_proper():
    Q = nearest_rotation(np.diag([1.0, 1.0, -1.0]))
    np.testing.assert_allclose(np.linalg.det(Q), 1.0)


def test_rotation_angle_known_and_tiny():
    Rz = rotvec_to_matrix(np.array([0.0, 0.0, np.radians(30.0)]))
    assert rotation_angle_deg(np.eye(3), Rz) == pytest.approx(30.0)
    tiny = rotvec_to_matrix(np.array([1e-9, 0.0, 0.0]))
    assert rotation_angle_deg(np.eye(3), tiny) == pytest.approx(np.degrees(1e-9), rel=1e-6)
    R = rotvec_to_matrix(ROTVECS)
    np.testing.assert_allclose(rotation_angle_deg(R, R), 0.0, atol=1e-6)
    assert rotation_angle_deg(R, R).shape == (6,)


@pytest.mark.parametrize("scale", [1.0, 1e-7, 0.0])
def test_left_jacobian_matches_finite_differences(scale):
    eps = 1e-6
    X = RNG.normal(size=3)
    for w in ROTVECS * scale:
        J = so3_left_jacobian(w)
        Y = rotvec_to_matrix(w) @ X
        numeric = np.stack([(rotvec_to_matrix(w + eps * e) @ X - rotvec_to_matrix(w - eps * e) @ X) / (2 * eps)
                            for e in np.eye(3)], axis=1)
        np.testing.assert_allclose(-skew(Y) @ J, numeric, atol=1e-8)


def test_left_jacobian_at_zero_is_identity():
    np.testing.assert_allclose(so3_left_jacobian(np.zeros((2, 3))), np.broadcast_to(np.eye(3), (2, 3, 3)))


def test_look_at_points_the_camera_at_the_target():
    eye = np.array([[0.0, 0.0, -2.0], [1.0, -0.5, 3.0]])
    target = np.array([[0.0, 0.0, 0.0], [0.2, 0.1, 0.0]])
    R, t = look_at(eye, target)
    np.testing.assert_allclose(R[0], np.eye(3), atol=1e-12)  # already looking down +z with y down
    camera_target = np.einsum("nij,nj->ni", R, target) + t
    np.testing.assert_allclose(camera_target[:, :2], 0.0, atol=1e-12)
    assert np.all(camera_target[:, 2] > 0)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    with pytest.raises(InvalidValue):
        look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
