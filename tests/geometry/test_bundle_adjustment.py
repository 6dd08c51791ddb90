"""lab.geometry.bundle_adjustment: the Jacobian's sparsity, the analytic derivatives, the solver."""

import cv2
import numpy as np
import pytest
import scipy.sparse

from lab.core import InvalidControl, InvalidValue
from lab.geometry.bundle_adjustment import BundleResult, bundle_adjust, bundle_sparsity, project_with_jacobians
from lab.geometry.rotations import look_at, matrix_to_rotvec, rotation_angle_deg, rotvec_to_matrix

K = np.array([[800.0, 0.0, 320.0], [0.0, 790.0, 240.0], [0.0, 0.0, 1.0]])


def _scene(views: int = 6, count: int = 300, seed: int = 0, visible: float = 0.7):
    """An orbit of cameras around a cube of points; each camera sees a random ``visible`` share."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(0.0, np.pi, views)
    eyes = np.stack([6 * np.cos(angles), -1.0 + 0 * angles, 6 * np.sin(angles)], axis=1)
    R, t = look_at(eyes, np.zeros_like(eyes))
    X = rng.uniform(-1.5, 1.5, (count, 3))
    cams = np.repeat(np.arange(views), count)
    pts = np.tile(np.arange(count), views)
    seen = rng.random(len(cams)) < visible
    seen[:2 * count] = True  # the first two cameras see everything: every point has two views
    cams, pts = cams[seen], pts[seen]
    Xc = np.einsum("mij,mj->mi", R[cams], X[pts]) + t[cams]
    uv = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2]
    return R, t, X, cams, pts, uv


def _perturb(R, t, X, seed=1, rot=0.002, trans=0.01, point=0.01):
    rng = np.random.default_rng(seed)
    R0 = rotvec_to_matrix(rng.normal(0, rot, (len(R), 3))) @ R
    t0 = t + rng.normal(0, trans, t.shape)
    R0[0], t0[0] = R[0], t[0]  # the gauge camera is exact
    return R0, t0, X + rng.normal(0, point, X.shape)


def _rms(K_, R, t, X, cams, pts, uv):
    Ks = np.broadcast_to(K_, (len(R), 3, 3))
    Xc = np.einsum("mij,mj->mi", R[cams], X[pts]) + t[cams]
    proj = np.einsum("mij,mj->mi", Ks[cams], Xc / Xc[:, 2:])[:, :2]
    return float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, axis=1))))


# --- bundle_sparsity ------------------------------------------------------------------------------
def test_sparsity_smoke_shape_and_type():
    A = bundle_sparsity(np.array([0, 1, 1]), np.array([0, 0, 1]), 2, 2)
    assert isinstance(A, scipy.sparse.csr_matrix)
    assert A.shape == (6, 2 * 6 + 2 * 3)
    assert A.nnz == 6 * 9


def test_sparsity_known_answer():
    A = bundle_sparsity(np.array([1, 0]), np.array([0, 1]), 2, 2).toarray()
    expected = np.zeros((4, 18), dtype=int)
    expected[0:2, 6:12] = 1  # observation 0: camera 1
    expected[0:2, 12:15] = 1  # ... and point 0
    expected[2:4, 0:6] = 1  # observation 1: camera 0
    expected[2:4, 15:18] = 1  # ... and point 1
    np.testing.assert_array_equal(A, expected)


def test_sparsity_with_shared_and_per_camera_intrinsics():
    cams, pts = np.array([0, 1, 2]), np.array([2, 1, 0])
    shared = bundle_sparsity(cams, pts, 3, 3, intrinsic_params=4).toarray()
    assert shared.shape == (6, 3 * 6 + 4 + 9)
    assert np.all(shared[:, 18:22] == 1)  # every row depends on the shared K
    own = bundle_sparsity(cams, pts, 3, 3, camera_params=10).toarray()
    assert own.shape == (6, 30 + 9)
    np.testing.assert_array_equal(own[2:4, 10:20], 1)
    assert own[2:4, :10].sum() == 0 and own[2:4, 20:30].sum() == 0


@pytest.mark.parametrize("camera_params, intrinsic_params", [(6, 0), (6, 4), (10, 0)])
def test_sparsity_matches_a_finite_difference_jacobian(camera_params, intrinsic_params):
    """The non-zero pattern of a numerical Jacobian (projection by cv2.projectPoints) is the pattern."""
    R, t, X, cams, pts, _ = _scene(views=3, count=5, seed=2, visible=0.6)
    n, p = len(R), len(X)
    Ks = np.broadcast_to(K, (n, 3, 3)).copy()

    def residuals(x):
        block = x[: n * camera_params].reshape(n, camera_params)
        shared = x[n * camera_params: n * camera_params + intrinsic_params]
        points = x[n * camera_params + intrinsic_params:].reshape(p, 3)
        out = []
        for c, j in zip(cams, pts):
            Kc = Ks[c].copy()
            f = block[c, 6:] if camera_params == 10 else shared if intrinsic_params else None
            if f is not None:
                Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2] = f
            uv, _ = cv2.projectPoints(points[j][None], block[c, :3], block[c, 3:6], Kc, None)
            out.append(uv.ravel())
        return np.concatenate(out)

    block = np.concatenate([matrix_to_rotvec(R), t] + ([np.tile([800.0, 790.0, 320.0, 240.0], (n, 1))]
                                                       if camera_params == 10 else []), axis=1)
    x0 = np.concatenate([block.ravel(), [800.0, 790.0, 320.0, 240.0][:intrinsic_params], X.ravel()])
    J = np.zeros((2 * len(cams), len(x0)))
    for k in range(len(x0)):
        step = np.zeros_like(x0)
        step[k] = 1e-6 * max(1.0, abs(x0[k]))
        J[:, k] = (residuals(x0 + step) - residuals(x0 - step)) / (2 * step[k])
    pattern = bundle_sparsity(cams, pts, n, p, camera_params=camera_params,
                              intrinsic_params=intrinsic_params).toarray()
    assert not np.any((np.abs(J) > 1e-9) & (pattern == 0))  # nothing outside the pattern
    # the pattern is tight: per observation (both rows together) every marked column matters
    # (u does not depend on t_y without skew, so rows are compared in pairs)
    touched = (np.abs(J[0::2]) + np.abs(J[1::2])) > 1e-9
    np.testing.assert_array_equal(touched, pattern[0::2].astype(bool))


def test_sparsity_rejects_bad_indices():
    with pytest.raises(InvalidValue, match="camera_indices"):
        bundle_sparsity(np.array([0, 3]), np.array([0, 1]), 3, 2)
    with pytest.raises(InvalidValue, match="point_indices"):
        bundle_sparsity(np.array([0, 1]), np.array([0, -1]), 3, 2)
    with pytest.raises(InvalidValue, match="same length"):
        bundle_sparsity(np.array([0, 1]), np.array([0]), 3, 2)
    with pytest.raises(InvalidValue, match="integers"):
        bundle_sparsity(np.array([0.0, 1.0]), np.array([0.0, 1.0]), 3, 2)


# --- project_with_jacobians -----------------------------------------------------------------------
def test_projection_jacobians_match_cv2_project_points():
    rng = np.random.default_rng(0)
    w, t, X = rng.normal(0, 0.5, (5, 3)), rng.normal(0, 0.2, (5, 3)) + [0, 0, 5], rng.normal(0, 1, (5, 3))
    intr = np.tile([800.0, 790.0, 320.0, 240.0], (5, 1))
    uv, J = project_with_jacobians(w, t, X, intr, np.zeros(5))
    for m in range(5):
        projected, jac = cv2.projectPoints(X[m][None], w[m], t[m], K, None)
        np.testing.assert_allclose(uv[m], projected.ravel(), rtol=1e-12)
        np.testing.assert_allclose(J["rotvec"][m], jac[:, 0:3], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(J["t"][m], jac[:, 3:6], rtol=1e-9)
        np.testing.assert_allclose(J["intrinsics"][m][:, :2], jac[:, 6:8], rtol=1e-9)
        np.testing.assert_allclose(J["intrinsics"][m][:, 2:], jac[:, 8:10], rtol=1e-9)
    # d(pixel)/d(point) by central differences
    h = 1e-6
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        plus, _ = project_with_jacobians(w, t, X + step, intr, np.zeros(5), jacobians=False)
        minus, _ = project_with_jacobians(w, t, X - step, intr, np.zeros(5), jacobians=False)
        np.testing.assert_allclose(J["point"][:, :, k], (plus - minus) / (2 * h), rtol=1e-5, atol=1e-5)


# --- bundle_adjust --------------------------------------------------------------------------------
def test_bundle_adjust_smoke_and_shapes():
    R, t, X, cams, pts, uv = _scene()
    result = bundle_adjust(K, *_perturb(R, t, X), cams, pts, uv, max_iterations=5)
    assert isinstance(result, BundleResult)
    assert result.R.shape == R.shape and result.t.shape == t.shape and result.points.shape == X.shape
    assert result.K.shape == (3, 3)
    assert result.cost_history.shape == (result.iterations + 1,)
    assert result.cost_history[0] == result.rms_before


@pytest.mark.parametrize("jacobian", ["analytic", "2-point"])
def test_bundle_adjust_recovers_exact_scene_up_to_gauge(jacobian):
    R, t, X, cams, pts, uv = _scene()
    R0, t0, X0 = _perturb(R, t, X)
    result = bundle_adjust(K, R0, t0, X0, cams, pts, uv, jacobian=jacobian)
    assert result.rms_before > 1.0
    assert result.rms_after < 1e-5
    np.testing.assert_array_equal(result.R[0], R[0])  # the gauge camera is held exactly
    np.testing.assert_array_equal(result.t[0], t[0])
    assert rotation_angle_deg(result.R, R).max() < 1e-5
    # translation and points up to the scale about camera 0's centre (one coordinate was held)
    c0 = -R[0].T @ t[0]
    centers = -np.einsum("nji,nj->ni", result.R, result.t)
    true_centers = -np.einsum("nji,nj->ni", R, t)
    scale = np.linalg.norm(centers[1:] - c0) / np.linalg.norm(true_centers[1:] - c0)
    assert abs(scale - 1.0) < 0.02
    np.testing.assert_allclose(centers - c0, scale * (true_centers - c0), atol=1e-5)
    np.testing.assert_allclose(result.points - c0, scale * (X - c0), atol=1e-5)


def test_bundle_adjust_with_noise_lowers_the_error_to_the_noise_level():
    R, t, X, cams, pts, uv = _scene(views=8, count=400, seed=3)
    noisy = uv + np.random.default_rng(4).normal(0, 0.5, uv.shape)
    R0, t0, X0 = _perturb(R, t, X, seed=5)
    history = []
    result = bundle_adjust(K, R0, t0, X0, cams, pts, noisy, on_iteration=lambda i, c: history.append((i, c)))
    assert result.rms_after < result.rms_before
    assert result.rms_after < 0.5 * np.sqrt(2)  # below the noise: the points absorb some of it
    assert result.rms_after == pytest.approx(_rms(result.K, result.R, result.t, result.points, cams, pts, noisy))
    assert rotation_angle_deg(result.R, R).max() < 0.5 * rotation_angle_deg(R0, R).max()
    assert [i for i, _ in history] == list(range(1, result.iterations + 1))
    np.testing.assert_allclose([c for _, c in history], result.cost_history[1:])


def test_bundle_adjust_with_outliers_and_huber_beats_linear_loss():
    R, t, X, cams, pts, uv = _scene(seed=6)
    rng = np.random.default_rng(7)
    bad = rng.random(len(uv)) < 0.03
    corrupted = uv.copy()
    corrupted[bad] += rng.normal(0, 30, (bad.sum(), 2))
    R0, t0, X0 = _perturb(R, t, X, seed=8)
    robust = bundle_adjust(K, R0, t0, X0, cams, pts, corrupted, loss="huber")
    plain = bundle_adjust(K, R0, t0, X0, cams, pts, corrupted, loss="linear")
    assert rotation_angle_deg(robust.R, R).max() < rotation_angle_deg(plain.R, R).max()


@pytest.mark.parametrize("shared", [True, False])
def test_bundle_adjust_refines_intrinsics(shared):
    R, t, X, cams, pts, uv = _scene(views=8, count=400, seed=9)
    K_wrong = K.copy()
    K_wrong[0, 0] *= 1.01
    K_wrong[1, 1] *= 0.99
    K_in = K_wrong if shared else np.stack([K_wrong] * len(R))
    result = bundle_adjust(K_in, R, t, X, cams, pts, uv, refine_intrinsics=True, max_iterations=100)
    assert result.K.shape == K_in.shape
    assert result.rms_after < 1e-3 < result.rms_before
    np.testing.assert_allclose(np.broadcast_to(result.K, (len(R), 3, 3))[:, 0, 0], K[0, 0], rtol=1e-3)  # 1 % off


def test_bundle_adjust_never_returns_a_worse_scene():
    R, t, X, cams, pts, uv = _scene()
    result = bundle_adjust(K, R, t, X, cams, pts, uv)  # exact already: nothing to gain
    assert not result.improved
    assert result.cost_history.shape == (result.iterations + 1,)
    assert result.rms_after == result.rms_before
    np.testing.assert_array_equal(result.R, R)
    np.testing.assert_array_equal(result.points, X)


def test_bundle_adjust_holds_every_fixed_camera():
    R, t, X, cams, pts, uv = _scene()
    R0, t0, X0 = _perturb(R, t, X)
    result = bundle_adjust(K, R0, t0, X0, cams, pts, uv, fixed_cameras=(0, 2))
    np.testing.assert_array_equal(result.R[2], R0[2])
    np.testing.assert_array_equal(result.t[2], t0[2])
    assert result.rms_after < result.rms_before


def test_bundle_adjust_rejects_bad_input():
    R, t, X, cams, pts, uv = _scene(views=3, count=20)
    with pytest.raises(InvalidValue, match="observations"):
        bundle_adjust(K, R, t, X, cams, pts, uv[:-1])
    with pytest.raises(InvalidValue, match="camera_indices"):
        bundle_adjust(K, R, t, X, cams + 1, pts, uv)
    with pytest.raises(InvalidValue, match="NaN"):
        bundle_adjust(K, R, t, np.full_like(X, np.nan), cams, pts, uv)
    with pytest.raises(InvalidValue, match="K"):
        bundle_adjust(np.stack([K, K]), R, t, X, cams, pts, uv)
    with pytest.raises(InvalidControl, match="loss"):
        bundle_adjust(K, R, t, X, cams, pts, uv, loss="l7")
    with pytest.raises(InvalidControl, match="fixed_cameras"):
        bundle_adjust(K, R, t, X, cams, pts, uv, fixed_cameras=(5,))


def test_bundle_adjust_progress_yields_live_iterations_and_returns_the_result():
    from lab.geometry.bundle_adjustment import bundle_adjust_progress

    R, t, X, cams, pts, uv = _scene()
    R0, t0, X0 = _perturb(R, t, X)
    progress = bundle_adjust_progress(K, R0, t0, X0, cams, pts, uv)
    seen = []
    try:
        while True:
            seen.append(next(progress))
    except StopIteration as stop:
        result = stop.value
    direct = bundle_adjust(K, R0, t0, X0, cams, pts, uv)
    assert [i for i, _ in seen] == list(range(1, result.iterations + 1))
    np.testing.assert_allclose([c for _, c in seen], direct.cost_history[1:])
    np.testing.assert_allclose(result.points, direct.points)


def test_bundle_adjust_progress_can_be_cancelled_and_reports_errors():
    from lab.geometry.bundle_adjustment import bundle_adjust_progress

    R, t, X, cams, pts, uv = _scene()
    progress = bundle_adjust_progress(K, *_perturb(R, t, X), cams, pts, uv)
    assert next(progress)[0] == 1
    progress.close()  # joins the worker: returns only once the solver has stopped
    with pytest.raises(InvalidValue, match="observations"):
        next(bundle_adjust_progress(K, R, t, X, cams, pts, uv[:-1]))


def test_bundle_adjust_guard_on_the_robust_cost_keeps_a_result_whose_rms_grew():
    """Gross outliers: Huber fits the inliers and lets the outliers' errors (and the RMS) grow."""
    R, t, X, cams, pts, uv = _scene(seed=10)
    rng = np.random.default_rng(11)
    bad = rng.random(len(uv)) < 0.05
    corrupted = uv.copy()
    corrupted[bad] += rng.normal(0, 50, (bad.sum(), 2))
    start = bundle_adjust(K, R, t, X, cams, pts, corrupted, loss="linear")  # least squares: outliers pull
    by_rms = bundle_adjust(K, start.R, start.t, start.points, cams, pts, corrupted, loss="huber")
    by_cost = bundle_adjust(K, start.R, start.t, start.points, cams, pts, corrupted, loss="huber",
                            guard="robust_cost")
    assert not by_rms.improved and by_rms.rms_after == by_rms.rms_before  # the RMS would have grown
    assert by_cost.improved and by_cost.rms_after > by_cost.rms_before
    with pytest.raises(InvalidControl, match="guard"):
        bundle_adjust(K, R, t, X, cams, pts, corrupted, guard="median")


def test_projection_jacobians_with_skew_and_shared_cameras_match_finite_differences():
    rng = np.random.default_rng(1)
    w, t = rng.normal(0, 0.5, (2, 3)), rng.normal(0, 0.2, (2, 3)) + [0, 0, 5]
    cameras = np.array([0, 1, 1, 0, 1])
    X = rng.normal(0, 1, (5, 3))
    intr = np.tile([800.0, 790.0, 320.0, 240.0], (5, 1))
    skews = np.full(5, 3.0)
    uv, J = project_with_jacobians(w, t, X, intr, skews, cameras=cameras)
    per_pair, _ = project_with_jacobians(w[cameras], t[cameras], X, intr, skews, jacobians=False)
    np.testing.assert_allclose(uv, per_pair, rtol=1e-14)
    h = 1e-6
    for index, name in enumerate(("rotvec", "t", "point", "intrinsics")):
        array = (w, t, X, intr)[index]
        for k in range(array.shape[1]):
            step = np.zeros_like(array)
            step[:, k] = h
            plus, minus = [w, t, X, intr], [w, t, X, intr]
            plus[index], minus[index] = array + step, array - step
            up, _ = project_with_jacobians(*plus, skews, cameras=cameras, jacobians=False)
            down, _ = project_with_jacobians(*minus, skews, cameras=cameras, jacobians=False)
            np.testing.assert_allclose(J[name][:, :, k], (up - down) / (2 * h), rtol=1e-5, atol=1e-5)


def test_bundle_adjust_keeps_per_camera_intrinsics_when_not_refining():
    R, t, X, cams, pts, uv = _scene()
    Ks = np.stack([K] * len(R))
    result = bundle_adjust(Ks, *_perturb(R, t, X), cams, pts, uv)
    assert result.K.shape == Ks.shape
    np.testing.assert_array_equal(result.K, Ks)
    assert result.rms_after < 1e-5


def test_bundle_adjust_is_equivariant_under_a_world_similarity():
    """Moving and scaling the whole world moves the adjusted scene the same way (the gauge follows it)."""
    R, t, X, cams, pts, noisy = _scene(seed=12)  # exact pixels: both runs converge tightly
    R0, t0, X0 = _perturb(R, t, X, seed=14)  # the scale-holding coordinate is perturbed too
    Q, s, d = rotvec_to_matrix([0.2, -0.4, 0.1]), 2.5, np.array([3.0, -1.0, 4.0])
    # X' = s Q X + d; a camera keeps its image when R' = R Q^T and t' = s t - R Q^T d
    moved = bundle_adjust(K, R0 @ Q.T, s * t0 - np.einsum("nij,j->ni", R0 @ Q.T, d), s * X0 @ Q.T + d,
                          cams, pts, noisy)
    plain = bundle_adjust(K, R0, t0, X0, cams, pts, noisy)
    assert moved.rms_after < 1e-5 and plain.rms_after < 1e-5
    np.testing.assert_allclose(moved.points, s * plain.points @ Q.T + d, atol=1e-5)
    assert rotation_angle_deg(moved.R, plain.R @ Q.T).max() < 1e-5


def test_bundle_adjust_groups_finite_differences_by_a_given_pattern():
    R, t, X, cams, pts, uv = _scene(views=5, count=120, seed=6)
    R0, t0, X0 = _perturb(R, t, X, seed=7)
    pattern = bundle_sparsity(cams, pts, len(R), len(X))
    default = bundle_adjust(K, R0, t0, X0, cams, pts, uv, jacobian="2-point", fix_scale=False)
    given = bundle_adjust(K, R0, t0, X0, cams, pts, uv, jacobian="2-point", fix_scale=False, sparsity=pattern.toarray())
    np.testing.assert_allclose(given.points, default.points, atol=1e-9)
    assert given.rms_after < 1e-3
    no_points = pattern.toarray()
    no_points[:, 6 * len(R):] = 0  # the point columns left out: points get no derivatives, the error stays
    stalled = bundle_adjust(K, R0, t0, X0, cams, pts, uv, jacobian="2-point", fix_scale=False, sparsity=no_points)
    assert stalled.rms_after > 10 * given.rms_after
    with pytest.raises(InvalidValue, match="sparsity"):
        bundle_adjust(K, R0, t0, X0, cams, pts, uv, jacobian="2-point", sparsity=no_points[:, :-1])
