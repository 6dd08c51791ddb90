"""lab.geometry.homogeneous: homogeneous coordinates, homographies, Hartley's normalization."""

import cv2
import numpy as np
import pytest

from lab.core import InvalidValue
from lab.geometry.homogeneous import apply_homography, from_homogeneous, hartley_normalization, to_homogeneous

RNG = np.random.default_rng(3)


def test_to_and_from_homogeneous_roundtrip_batched():
    points = RNG.normal(size=(2, 5, 3))
    h = to_homogeneous(points)
    assert h.shape == (2, 5, 4)
    np.testing.assert_array_equal(h[..., 3], 1.0)
    np.testing.assert_allclose(from_homogeneous(h * 2.5), points)


def test_from_homogeneous_matches_opencv():
    h = RNG.normal(size=(7, 3))
    np.testing.assert_allclose(from_homogeneous(h), cv2.convertPointsFromHomogeneous(h)[:, 0], rtol=1e-6)


def test_homogeneous_rejects_bad_shapes():
    with pytest.raises(InvalidValue):
        to_homogeneous(np.zeros(3))
    with pytest.raises(InvalidValue):
        from_homogeneous(np.zeros((4, 1)))


def test_apply_homography_matches_perspective_transform():
    H = np.array([[1.2, 0.1, 30.0], [-0.05, 0.9, 12.0], [1e-3, 2e-3, 1.0]])
    points = RNG.uniform(0, 100, size=(9, 2))
    expected = cv2.perspectiveTransform(points[None], H)[0]
    np.testing.assert_allclose(apply_homography(H, points), expected, rtol=1e-9)


def test_apply_homography_broadcasts_a_batch_of_homographies():
    H = np.stack([np.eye(3), np.diag([2.0, 2.0, 1.0])])
    points = RNG.normal(size=(2, 4, 2))
    out = apply_homography(H, points)
    np.testing.assert_allclose(out[0], points[0])
    np.testing.assert_allclose(out[1], 2 * points[1])
    with pytest.raises(InvalidValue):
        apply_homography(np.eye(4), points)


def test_hartley_normalization_centres_and_scales():
    points = RNG.uniform(100, 600, size=(3, 20, 2))
    T, normalized = hartley_normalization(points)
    assert T.shape == (3, 3, 3) and normalized.shape == points.shape
    np.testing.assert_allclose(normalized.mean(axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(normalized, axis=-1).mean(axis=1), np.sqrt(2.0))
    np.testing.assert_allclose(apply_homography(T, points), normalized, atol=1e-12)


def test_hartley_normalization_3d_uses_sqrt3():
    _, normalized = hartley_normalization(RNG.normal(size=(30, 3)) + 5)
    assert np.linalg.norm(normalized, axis=-1).mean() == pytest.approx(np.sqrt(3.0))


def test_hartley_normalization_mask_ignores_padding():
    points = RNG.uniform(0, 10, size=(12, 2))
    padded = np.concatenate([points, np.full((5, 2), 1e6)])
    mask = np.arange(17) < 12
    T_masked, _ = hartley_normalization(padded, mask)
    T_plain, _ = hartley_normalization(points)
    np.testing.assert_allclose(T_masked, T_plain)


def test_hartley_normalization_rejects_degenerate_input():
    with pytest.raises(InvalidValue):
        hartley_normalization(np.ones((5, 2)))
    with pytest.raises(InvalidValue):
        hartley_normalization(np.zeros((5, 2)), mask=np.zeros(5, dtype=bool))
    with pytest.raises(InvalidValue):
        hartley_normalization(np.zeros((5, 2)), mask=np.ones(4, dtype=bool))
