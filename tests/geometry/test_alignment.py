"""The similarity alignment (Umeyama 1991) against a known similarity and against scikit-image."""

import numpy as np
import pytest

from lab.core.errors import InvalidValue
from lab.geometry.alignment import (Similarity, align_cameras, apply_similarity, camera_centers,
                                    similarity_of_cameras, umeyama)
from lab.geometry.rotations import look_at, rotvec_to_matrix

KNOWN = Similarity(2.5, rotvec_to_matrix(np.array([0.3, -0.2, 0.9])), np.array([1.0, -2.0, 0.5]))


def _cameras(rng, count=8):
    eyes = rng.normal(size=(count, 3)) * 3.0
    return look_at(eyes, np.zeros_like(eyes), (0.0, 0.0, 1.0))


def test_umeyama_recovers_a_known_similarity_and_matches_scikit_image():
    from skimage.transform import SimilarityTransform

    rng = np.random.default_rng(0)
    source = rng.normal(size=(30, 3))
    target = apply_similarity(KNOWN, source)
    s, Q, d = umeyama(source, target)
    assert s == pytest.approx(2.5, abs=1e-12)
    np.testing.assert_allclose(Q, KNOWN.Q, atol=1e-12)
    np.testing.assert_allclose(d, KNOWN.offset, atol=1e-12)
    noisy = target + rng.normal(0.0, 0.05, target.shape)
    s, Q, d = umeyama(source, noisy)
    reference = SimilarityTransform.from_estimate(source, noisy)
    ours = np.eye(4)
    ours[:3, :3], ours[:3, 3] = s * Q, d
    np.testing.assert_allclose(ours, reference.params, atol=1e-10)


def test_cameras_moved_by_a_similarity_keep_their_images_and_are_aligned_back():
    rng = np.random.default_rng(1)
    R, t = _cameras(rng)
    R2, t2 = similarity_of_cameras(KNOWN, R, t)
    X = rng.normal(size=(20, 3))
    before = np.einsum("nij,pj->npi", R, X) + t[:, None]
    after = np.einsum("nij,pj->npi", R2, apply_similarity(KNOWN, X)) + t2[:, None]
    np.testing.assert_allclose(after, KNOWN.scale * before, atol=1e-10)       # same pixels: z scales too
    np.testing.assert_allclose(camera_centers(R2, t2), apply_similarity(KNOWN, camera_centers(R, t)),
                               atol=1e-10)
    found = align_cameras(R2, t2, R, t)                                        # back onto the originals
    inverse = KNOWN.inverse()
    assert found.scale == pytest.approx(inverse.scale, abs=1e-12)
    np.testing.assert_allclose(found.Q, inverse.Q, atol=1e-10)
    np.testing.assert_allclose(found.offset, inverse.offset, atol=1e-10)
    R3, t3 = similarity_of_cameras(found, R2, t2)
    np.testing.assert_allclose(R3, R, atol=1e-10)
    np.testing.assert_allclose(t3, t, atol=1e-10)


def test_cameras_on_a_line_or_too_few_are_refused():
    rng = np.random.default_rng(2)
    R, t = _cameras(rng, 2)
    with pytest.raises(InvalidValue, match="do not span a plane"):
        align_cameras(R, t, R, t)
    R, _ = _cameras(rng, 5)
    line = np.outer(np.arange(5.0), [0.2, 0.1, 1.0])
    t = -np.einsum("nij,nj->ni", R, line)
    with pytest.raises(InvalidValue, match="do not span a plane"):
        align_cameras(R, t, R, t)
    with pytest.raises(InvalidValue, match="NaN"):
        align_cameras(R, np.full_like(t, np.nan), R, t)
