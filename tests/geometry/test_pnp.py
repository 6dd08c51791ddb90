"""lab.geometry.pnp: linear PnP (DLT), PnP in RANSAC, the non-linear refinement; against cv2.solvePnP*."""

import cv2
import numpy as np
import pytest

from lab.core import InvalidControl, InvalidValue
from lab.geometry.pnp import PnPResult, pnp_dlt, pnp_ransac, refine_pnp, reprojection_errors
from lab.geometry.rotations import matrix_to_rotvec, rotation_angle_deg, rotvec_to_matrix

K = np.array([[800.0, 0.0, 320.0], [0.0, 790.0, 240.0], [0.0, 0.0, 1.0]])
R_TRUE = rotvec_to_matrix([0.1, -0.3, 0.2])
T_TRUE = np.array([0.2, -0.1, 5.0])


def _scene(count: int = 100, noise: float = 0.0, seed: int = 0, K: np.ndarray = K):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.0, 1.0, (count, 3))
    Xc = X @ R_TRUE.T + T_TRUE
    x = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2]
    return X, x + rng.normal(0.0, noise, x.shape)


def _rms(R, t, X, x):
    return float(np.sqrt(np.mean(reprojection_errors(R, t, X, x, K) ** 2)))


# --- pnp_dlt --------------------------------------------------------------------------------------
def test_dlt_smoke_and_shapes():
    X, x = _scene()
    R, t = pnp_dlt(X, x, K)
    assert R.shape == (3, 3) and t.shape == (3,)
    assert R.dtype == np.float64 and t.dtype == np.float64


@pytest.mark.parametrize("count", [6, 7, 20, 500])
def test_dlt_recovers_exact_pose(count):
    X, x = _scene(count)
    R, t = pnp_dlt(X, x, K)
    assert rotation_angle_deg(R, R_TRUE) < 1e-8
    np.testing.assert_allclose(t, T_TRUE, atol=1e-9)


def test_dlt_rotation_is_proper_and_points_are_in_front():
    X, x = _scene(50, noise=2.0, seed=1)
    R, t = pnp_dlt(X, x, K)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    assert np.all((X @ R.T + t)[:, 2] > 0)
    assert rotation_angle_deg(R, R_TRUE) < 2.0


def test_dlt_is_invariant_to_a_world_similarity():
    """Moving the world by a similarity moves the recovered camera the same way (H&Z 7.1 normalization)."""
    X, x = _scene(30)
    Q = rotvec_to_matrix([0.3, 0.5, -0.2])
    s, d = 3.0, np.array([10.0, -4.0, 2.0])
    Y = s * X @ Q.T + d  # Y = s Q X + d, so X = Q^T (Y - d) / s
    R, t = pnp_dlt(Y, x, K)
    # x ~ R_TRUE X + T_TRUE = R_TRUE Q^T (Y - d) / s + T_TRUE  ~  R_TRUE Q^T Y + (s T_TRUE - R_TRUE Q^T d)
    assert rotation_angle_deg(R, R_TRUE @ Q.T) < 1e-7
    np.testing.assert_allclose(t, s * T_TRUE - R_TRUE @ Q.T @ d, atol=1e-7)


def test_dlt_close_to_cv2_on_noisy_data():
    X, x = _scene(200, noise=0.5, seed=2)
    R, t = pnp_dlt(X, x, K)
    _, rvec, tvec = cv2.solvePnP(X, x, K, None, flags=cv2.SOLVEPNP_EPNP)
    assert rotation_angle_deg(R, rotvec_to_matrix(rvec.ravel())) < 0.5
    assert _rms(R, t, X, x) < 2.0 * _rms(rotvec_to_matrix(rvec.ravel()), tvec.ravel(), X, x)


@pytest.mark.parametrize("count", [0, 3, 5])
def test_dlt_rejects_too_few_points(count):
    X, x = _scene(10)
    with pytest.raises(InvalidValue, match="at least 6"):
        pnp_dlt(X[:count], x[:count], K)


def test_dlt_rejects_nan_and_mismatched_shapes():
    X, x = _scene(10)
    bad = X.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InvalidValue, match="NaN"):
        pnp_dlt(bad, x, K)
    with pytest.raises(InvalidValue, match="points2d"):
        pnp_dlt(X, x[:9], K)
    with pytest.raises(InvalidValue, match="points3d"):
        pnp_dlt(X[:, :2], x, K)
    with pytest.raises(InvalidValue, match="K"):
        pnp_dlt(X, x, np.eye(4))


def test_dlt_rejects_coplanar_points():
    X, x = _scene(20)
    X[:, 2] = 0.5  # all on a plane
    Xc = X @ R_TRUE.T + T_TRUE
    x = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2]
    with pytest.raises(InvalidValue, match="coplanar"):
        pnp_dlt(X, x, K)


# --- pnp_ransac -----------------------------------------------------------------------------------
def _with_outliers(fraction: float, seed: int = 3):
    X, x = _scene(200, noise=0.5, seed=seed)
    rng = np.random.default_rng(seed + 100)
    outliers = rng.random(len(X)) < fraction
    x = x.copy()
    x[outliers] = rng.uniform([0, 0], [640, 480], (outliers.sum(), 2))
    return X, x, outliers


def test_ransac_smoke_and_result_type():
    X, x, outliers = _with_outliers(0.3)
    result = pnp_ransac(X, x, K, rng=np.random.default_rng(0))
    assert isinstance(result, PnPResult)
    assert result.R.shape == (3, 3) and result.t.shape == (3,) and result.inliers.shape == (200,)
    assert result.inliers.dtype == bool
    assert result.iterations >= 1 and result.rms_px > 0


@pytest.mark.parametrize("fraction", [0.0, 0.3, 0.5])
def test_ransac_finds_the_inliers_and_the_pose(fraction):
    X, x, outliers = _with_outliers(fraction)
    result = pnp_ransac(X, x, K, rng=np.random.default_rng(1))
    assert np.mean(result.inliers == ~outliers) > 0.97
    assert rotation_angle_deg(result.R, R_TRUE) < 0.5
    assert result.rms_px < 1.5


def test_ransac_adapts_its_iteration_count():
    clean = pnp_ransac(*_with_outliers(0.0)[:2], K, rng=np.random.default_rng(2))
    dirty = pnp_ransac(*_with_outliers(0.5)[:2], K, rng=np.random.default_rng(2))
    assert clean.iterations < 20 < dirty.iterations <= 2000


def test_ransac_is_reproducible_with_the_same_seed():
    X, x, _ = _with_outliers(0.4)
    a = pnp_ransac(X, x, K, rng=np.random.default_rng(7))
    b = pnp_ransac(X, x, K, rng=np.random.default_rng(7))
    np.testing.assert_array_equal(a.inliers, b.inliers)
    np.testing.assert_array_equal(a.R, b.R)


def test_ransac_agrees_with_cv2_solve_pnp_ransac():
    X, x, outliers = _with_outliers(0.4, seed=5)
    ours = pnp_ransac(X, x, K, threshold_px=4.0, rng=np.random.default_rng(0))
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(X, x, K, None, reprojectionError=4.0, confidence=0.999,
                                                 iterationsCount=2000)
    assert ok
    theirs = np.zeros(len(X), dtype=bool)
    theirs[inliers.ravel()] = True
    assert np.mean(ours.inliers == theirs) > 0.97
    assert rotation_angle_deg(ours.R, rotvec_to_matrix(rvec.ravel())) < 0.5


def test_ransac_fails_clearly_on_pure_noise():
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (30, 3))
    x = rng.uniform(0, 640, (30, 2))
    with pytest.raises(InvalidValue, match="no pose"):
        pnp_ransac(X, x, K, threshold_px=0.01, max_iterations=50, rng=rng)


def test_ransac_rejects_bad_controls():
    X, x, _ = _with_outliers(0.0)
    with pytest.raises(InvalidControl, match="threshold_px"):
        pnp_ransac(X, x, K, threshold_px=0.0, rng=np.random.default_rng(0))
    with pytest.raises(InvalidValue, match="confidence"):
        pnp_ransac(X, x, K, confidence=1.0, rng=np.random.default_rng(0))
    with pytest.raises(InvalidValue, match="at least 6"):
        pnp_ransac(X[:5], x[:5], K, rng=np.random.default_rng(0))


# --- refine_pnp -----------------------------------------------------------------------------------
def test_refine_lowers_the_error_of_the_dlt():
    X, x = _scene(100, noise=1.0, seed=4)
    R0, t0 = pnp_dlt(X, x, K)
    R1, t1 = refine_pnp(R0, t0, X, x, K)
    assert R1.shape == (3, 3) and t1.shape == (3,)
    assert _rms(R1, t1, X, x) < _rms(R0, t0, X, x)
    assert rotation_angle_deg(R1, R_TRUE) < rotation_angle_deg(R0, R_TRUE)


def test_refine_with_linear_loss_matches_cv2_solve_pnp_iterative():
    X, x = _scene(100, noise=1.0, seed=4)
    R0, t0 = pnp_dlt(X, x, K)
    R1, t1 = refine_pnp(R0, t0, X, x, K, loss="linear")
    _, rvec, tvec = cv2.solvePnP(X, x, K, None, rvec=matrix_to_rotvec(R0).reshape(3, 1), tvec=t0.reshape(3, 1).copy(),
                                 useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    assert rotation_angle_deg(R1, rotvec_to_matrix(rvec.ravel())) < 1e-4
    np.testing.assert_allclose(t1, tvec.ravel(), atol=1e-5)


def test_refine_converges_from_a_perturbed_pose():
    X, x = _scene(60)
    R0 = rotvec_to_matrix([0.05, 0.02, -0.04]) @ R_TRUE
    R1, t1 = refine_pnp(R0, T_TRUE + [0.1, -0.1, 0.2], X, x, K)
    assert rotation_angle_deg(R1, R_TRUE) < 1e-6
    np.testing.assert_allclose(t1, T_TRUE, atol=1e-7)


def test_refine_never_raises_the_error():
    X, x = _scene(40)
    R1, t1 = refine_pnp(R_TRUE, T_TRUE, X, x, K)  # already exact: nothing to gain, input kept
    np.testing.assert_array_equal(R1, R_TRUE)
    np.testing.assert_array_equal(t1, T_TRUE)


def test_refine_rejects_bad_input():
    X, x = _scene(10)
    with pytest.raises(InvalidControl, match="loss"):
        refine_pnp(R_TRUE, T_TRUE, X, x, K, loss="l7")
    with pytest.raises(InvalidValue, match="R"):
        refine_pnp(np.eye(2), T_TRUE, X, x, K)
    with pytest.raises(InvalidValue, match="NaN"):
        refine_pnp(R_TRUE, T_TRUE, X, np.full_like(x, np.nan), K)
