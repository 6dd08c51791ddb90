"""Perspective-n-Point: a calibrated camera's pose from 2D-3D correspondences.

Given world points ``X_i`` ``(N, 3)``, their pixels ``x_i`` ``(N, 2)`` and the intrinsics ``K``,
find ``R``, ``t`` with ``x_i ~ K (R X_i + t)`` (DESIGN.md section 3: ``X_c = R X_w + t``).

* :func:`pnp_dlt` - the linear solution: the ``3 x 4`` matrix ``[R | t]`` up to scale as the null
  vector of a ``2N x 12`` system in normalized coordinates, then projected onto a rotation
  (Hartley & Zisserman section 7.1).
* :func:`pnp_ransac` - :func:`pnp_dlt` on minimal samples of 6 inside RANSAC with the adaptive
  sample count of :mod:`lab.geometry.robust`.
* :func:`refine_pnp` - Levenberg-Marquardt-like refinement of the reprojection error over the
  axis-angle rotation and the translation (``scipy.optimize.least_squares``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from lab.core.errors import InvalidControl, InvalidValue
from lab.geometry.bundle_adjustment import LOSSES, project_with_jacobians, robust_loss
from lab.geometry.camera import as_intrinsics, pixels_to_normalized
from lab.geometry.homogeneous import hartley_normalization
from lab.geometry.robust import random_samples, ransac_iterations
from lab.geometry.rotations import matrix_to_rotvec, nearest_rotation, rotvec_to_matrix

#: Correspondences the 11-degree-of-freedom DLT needs (each gives two equations).
MIN_CORRESPONDENCES = 6


def _correspondences(points3d: object, points2d: object, minimum: int = MIN_CORRESPONDENCES):
    X = np.asarray(points3d, dtype=np.float64)
    x = np.asarray(points2d, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InvalidValue("points3d", f"expected (N, 3) world points, got shape {X.shape}")
    if x.shape != (len(X), 2):
        raise InvalidValue("points2d", f"expected ({len(X)}, 2) pixels matching the {len(X)} world points, "
                                       f"got shape {x.shape}")
    if len(X) < minimum:
        raise InvalidValue("points3d", f"the linear PnP (DLT) needs at least {minimum} 2D-3D "
                                       f"correspondences, got {len(X)}")
    if not np.all(np.isfinite(X)):
        raise InvalidValue("points3d", "contains NaN or infinite entries")
    if not np.all(np.isfinite(x)):
        raise InvalidValue("points2d", "contains NaN or infinite entries")
    return X, x


def dlt_projection_matrices(X: np.ndarray, x: np.ndarray, *,
                            hartley: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Batched DLT of ``B`` sets: world ``(B, n, 3)``, normalized image points ``(B, n, 2)`` -> ``P``
    ``(B, 3, 4)``.

    Each ``P`` is the null vector of its ``2n x 12`` system (H&Z eq. (7.2)), solved on Hartley-normalized
    point sets unless ``hartley`` is False (lesson 04's mistake of that name uses it), the normalizations
    undone, the sign chosen so that the points' depths are positive. Also returns the singular values of
    the systems ``(B, 12)`` (to judge degeneracy).
    """
    T3, Xn = hartley_normalization(X) if hartley else (np.broadcast_to(np.eye(4), (len(X), 4, 4)), X)
    T2, xn = hartley_normalization(x) if hartley else (np.broadcast_to(np.eye(3), (len(x), 3, 3)), x)
    b, n = X.shape[:2]
    Xh = np.concatenate([Xn, np.ones((b, n, 1))], axis=2)  # (B, n, 4)
    zeros = np.zeros_like(Xh)
    # u = p1.X / p3.X, v = p2.X / p3.X: rows [X^T, 0, -u X^T] and [0, X^T, -v X^T] (H&Z eq. (7.2))
    row_u = np.concatenate([Xh, zeros, -xn[..., 0:1] * Xh], axis=2)
    row_v = np.concatenate([zeros, Xh, -xn[..., 1:2] * Xh], axis=2)
    A = np.concatenate([row_u, row_v], axis=1)  # (B, 2n, 12)
    _, s, Vt = np.linalg.svd(A, full_matrices=False)
    P = Vt[:, -1].reshape(b, 3, 4)
    P = np.linalg.solve(T2, P) @ T3  # undo both normalizations: P = T2^-1 P~ T3
    # sign: the points must be in front of the camera (positive third coordinate of P X)
    depth = np.einsum("bj,bnj->bn", P[:, 2, :3], X) + P[:, 2, 3][:, None]
    sign = np.where(np.sum(np.sign(depth), axis=1) < 0, -1.0, 1.0)
    return P * sign[:, None, None], s


def _dlt_batch(X: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched DLT on ``B`` sets: world ``(B, n, 3)``, normalized image points ``(B, n, 2)``.

    Returns ``R`` ``(B, 3, 3)``, ``t`` ``(B, 3)`` and the singular values of the ``2n x 12``
    systems ``(B, 12)`` (to judge degeneracy).
    """
    P, s = dlt_projection_matrices(X, x)
    M = P[:, :, :3]
    sv = np.linalg.svd(M, compute_uv=False)
    R = nearest_rotation(M)
    scale = sv.mean(axis=1)  # P = scale [R | t] up to noise
    scale = np.where(scale > 0, scale, 1.0)
    t = P[:, :, 3] / scale[:, None]
    return R, t, s


def pnp_dlt(points3d: np.ndarray, points2d: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear PnP: the camera pose ``(R, t)`` from ``N >= 6`` 2D-3D correspondences and known ``K``.

    1. Normalized coordinates ``K^-1 x`` (the calibrated camera is ``[R | t]``), then Hartley's
       normalization of both point sets for conditioning (H&Z section 4.4.4).
    2. Each correspondence gives two rows of ``A p = 0`` for the 12 entries of ``P = [M | p]``
       (H&Z section 7.1, eq. (7.2)); ``p`` is the right singular vector of ``A`` with the smallest
       singular value. The normalizations are undone.
    3. The sign of ``P`` makes the points' depths positive; ``M = lambda R`` up to noise, so ``R``
       is the nearest rotation to ``M`` (SVD, ``U V^T`` with ``det = +1``) and the scale
       ``lambda`` the mean singular value of ``M``; ``t = p / lambda``.

    Args:
        points3d: ``(N, 3)`` world points, N >= 6, not coplanar.
        points2d: ``(N, 2)`` their pixels (undistorted).
        K: ``(3, 3)`` intrinsics.

    Returns ``R`` ``(3, 3)`` (a proper rotation) and ``t`` ``(3,)`` with ``X_c = R X + t``.

    Raises :class:`InvalidValue` for fewer than 6 correspondences, NaNs, and degenerate
    configurations: coplanar world points (then the 12 x 12 system has a 4-dimensional null space
    and the 11-dof DLT cannot choose; a planar scene needs a homography-based PnP such as
    ``cv2.solvePnP(..., flags=cv2.SOLVEPNP_IPPE)``), or points and camera centre on a twisted
    cubic (H&Z section 7.1.2, "degenerate configurations").

    No OpenCV flag gives the bare DLT: ``cv2.solvePnP(..., flags=cv2.SOLVEPNP_ITERATIVE)``
    initialises a non-planar scene with this DLT (calib3d's ``cvFindExtrinsicCameraParams2``) and
    then runs Levenberg-Marquardt (:func:`refine_pnp`); ``cv2.SOLVEPNP_EPNP`` is another linear
    solution the tests compare with.
    """
    X, x = _correspondences(points3d, points2d)
    K = as_intrinsics(K)
    centred = X - X.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False)
    if spread[0] <= 0 or spread[2] <= 1e-9 * spread[0]:
        raise InvalidValue("points3d", "the world points are coplanar (or collinear): degenerate for the "
                                       "11-dof DLT, whose system then has a multi-dimensional null space; "
                                       "use a planar PnP (homography, cv2.SOLVEPNP_IPPE) for a planar scene")
    R, t, s = _dlt_batch(X[None], pixels_to_normalized(x, K)[None])
    if s[0, -2] <= 1e-10 * s[0, 0]:
        raise InvalidValue("points3d", "degenerate configuration: the DLT system has more than one null "
                                       "vector (points and camera centre on a twisted cubic, or repeated "
                                       "points)")
    return R[0], t[0]


def reprojection_errors(R: np.ndarray, t: np.ndarray, points3d: np.ndarray, points2d: np.ndarray,
                        K: np.ndarray) -> np.ndarray:
    """Distance in pixels between each projected point and its observation, ``(N,)``; ``inf`` behind
    the camera."""
    Xc = points3d @ np.asarray(R).T + np.asarray(t)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = Xc[:, :2] / Xc[:, 2:3]
    uv = xy @ K[:2, :2].T + K[:2, 2]
    errors = np.linalg.norm(uv - points2d, axis=1)
    return np.where((Xc[:, 2] > 0) & np.isfinite(errors), errors, np.inf)


def _rms(errors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(errors * errors))) if len(errors) else 0.0


@dataclass(frozen=True)
class PnPResult:
    """The pose found by :func:`pnp_ransac`.

    ``R`` ``(3, 3)``, ``t`` ``(3,)``; ``inliers`` ``(N,)`` bool (reprojection error below the
    threshold and in front of the camera); ``iterations``: samples drawn; ``rms_px``: RMS
    reprojection error of the inliers.
    """

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    iterations: int
    rms_px: float


def pnp_ransac(points3d: np.ndarray, points2d: np.ndarray, K: np.ndarray, *, threshold_px: float = 4.0,
               confidence: float = 0.999, max_iterations: int = 2000, rng: np.random.Generator) -> PnPResult:
    """Robust PnP: :func:`pnp_dlt` on random minimal samples of 6 correspondences (RANSAC).

    Each sample's pose scores every correspondence by its reprojection error ``e``; the MSAC
    score ``sum min(e^2, threshold^2)`` picks the best pose, whose inliers (``e < threshold``,
    in front of the camera) update the inlier ratio ``w`` and with it the number of samples
    needed, ``log(1 - confidence) / log(1 - w^6)`` (:func:`lab.geometry.robust.ransac_iterations`).
    Samples are solved in batches with one batched SVD. The final pose is the DLT on all inliers
    of the best sample, re-scored (twice: inliers of the refit, refit again).

    Args:
        points3d: ``(N, 3)``; points2d: ``(N, 2)``; K: ``(3, 3)``.
        threshold_px: inlier threshold on the reprojection error, pixels.
        confidence: probability of drawing at least one all-inlier sample.
        max_iterations: most samples.
        rng: the random generator (the runner supplies it).

    Returns a :class:`PnPResult`. Raises :class:`InvalidValue` when fewer than 6 correspondences
    are given or no pose has 6 inliers (field ``points2d``, with the counts).

    Corresponds to ``cv2.solvePnPRansac(..., flags=cv2.SOLVEPNP_EPNP / ITERATIVE)``.

    Reference: Fischler and Bolles (1981); Hartley & Zisserman (2nd ed.), sections 4.7.1 and 7.1;
    P. Torr and A. Zisserman, "MLESAC", CVIU 78 (2000) for the truncated-quadratic score.
    """
    X, x = _correspondences(points3d, points2d)
    K = as_intrinsics(K)
    if not float(threshold_px) > 0:
        raise InvalidControl("threshold_px", f"must be positive, got {threshold_px}")
    if int(max_iterations) < 1:
        raise InvalidControl("max_iterations", f"must be at least 1, got {max_iterations}")
    n = len(X)
    normalized = pixels_to_normalized(x, K)
    threshold2 = float(threshold_px) ** 2
    needed = ransac_iterations(0.0, MIN_CORRESPONDENCES, confidence, int(max_iterations))
    best_score, best_pose, best_count = np.inf, None, 0
    drawn = 0
    batch = 64
    while drawn < needed:
        count = min(batch, needed - drawn)
        samples = random_samples(rng, n, MIN_CORRESPONDENCES, count)
        with np.errstate(all="ignore"):
            try:
                Rs, ts, _ = _dlt_batch(X[samples], normalized[samples])
            except (np.linalg.LinAlgError, InvalidValue):  # a batch with coincident sample points
                Rs, ts = _dlt_each(X[samples], normalized[samples])
            Xc = np.einsum("bij,nj->bni", Rs, X) + ts[:, None, :]
            xy = Xc[..., :2] / Xc[..., 2:3]
            uv = xy @ K[:2, :2].T + K[:2, 2]
            e2 = np.sum((uv - x) ** 2, axis=2)
        e2 = np.where((Xc[..., 2] > 0) & np.isfinite(e2), e2, np.inf)
        scores = np.minimum(e2, threshold2).sum(axis=1)
        inlier_counts = (e2 < threshold2).sum(axis=1)
        for k in range(count):  # sequential, so the adaptive count is exactly RANSAC's
            drawn += 1
            if scores[k] < best_score and inlier_counts[k] >= MIN_CORRESPONDENCES:
                best_score, best_pose, best_count = scores[k], (Rs[k], ts[k]), int(inlier_counts[k])
                needed = ransac_iterations(best_count / n, MIN_CORRESPONDENCES, confidence,
                                           int(max_iterations))
            if drawn >= needed:
                break
    if best_pose is None:
        raise InvalidValue("points2d", f"RANSAC found no pose with at least {MIN_CORRESPONDENCES} of the {n} "
                                       f"correspondences within {threshold_px} px after {drawn} samples")
    R, t = best_pose
    inliers = reprojection_errors(R, t, X, x, K) < float(threshold_px)
    for _ in range(2):  # refit on all inliers while that keeps enough of them
        if inliers.sum() < MIN_CORRESPONDENCES:
            break
        try:
            R_fit, t_fit = pnp_dlt(X[inliers], x[inliers], K)
        except InvalidValue:
            break
        refit_inliers = reprojection_errors(R_fit, t_fit, X, x, K) < float(threshold_px)
        if refit_inliers.sum() < inliers.sum():
            break
        R, t, inliers = R_fit, t_fit, refit_inliers
    errors = reprojection_errors(R, t, X, x, K)
    return PnPResult(R=R, t=t, inliers=inliers, iterations=drawn, rms_px=_rms(errors[inliers]))


def _dlt_each(X: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_dlt_batch` one sample at a time; a degenerate sample gives a pose that scores nothing."""
    Rs, ts = np.tile(np.eye(3), (len(X), 1, 1)), np.full((len(X), 3), np.nan)
    for k in range(len(X)):
        try:
            R, t, _ = _dlt_batch(X[k:k + 1], x[k:k + 1])
            Rs[k], ts[k] = R[0], t[0]
        except (np.linalg.LinAlgError, InvalidValue):
            pass
    return Rs, ts


def refine_pnp(R: np.ndarray, t: np.ndarray, points3d: np.ndarray, points2d: np.ndarray, K: np.ndarray, *,
               loss: str = "huber", f_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Non-linear PnP: minimize the (robust) reprojection error over the pose, from a starting pose.

    Parameters are the axis-angle rotation ``w`` (``R = exp([w]_x)``) and ``t``; residuals
    ``pi(K (R(w) X_i + t)) - x_i`` ``(2N,)`` with the analytic Jacobian (``dY/dw = -[R X]_x
    J_l(w)``, :func:`lab.geometry.bundle_adjustment.project_with_jacobians`), solved by
    ``scipy.optimize.least_squares(method="trf", loss=loss, f_scale=f_scale)``.

    Args:
        R, t: starting pose ``(3, 3)``, ``(3,)`` (e.g. :func:`pnp_dlt`'s on the RANSAC inliers).
        points3d: ``(N, 3)``; points2d: ``(N, 2)``; K: ``(3, 3)``. Pass the inliers: the RMS
            over what is passed is what must not grow.
        loss, f_scale: robust loss and its scale in pixels.

    Returns the refined ``(R, t)``; the input pose when the RMS reprojection error over the given
    correspondences does not fall (so the error never rises).

    Corresponds to ``cv2.solvePnPRefineLM`` (and ``cv2.solvePnP(..., useExtrinsicGuess=True,
    flags=cv2.SOLVEPNP_ITERATIVE)``).

    Reference: Hartley & Zisserman (2nd ed.), section 7.2 (minimizing geometric error) and A6.2.
    """
    X, x = _correspondences(points3d, points2d, minimum=3)
    K = as_intrinsics(K)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise InvalidValue("R", "expected a finite (3, 3) rotation and (3,) translation, "
                                f"got {R.shape}, {t.shape}")
    if loss not in LOSSES:
        raise InvalidControl("loss", f"unknown loss {loss!r}; losses are {list(LOSSES)}")
    if not float(f_scale) > 0:
        raise InvalidControl("f_scale", f"must be positive, got {f_scale}")
    n = len(X)
    intrinsics = np.broadcast_to([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], (n, 4))
    skews = np.full(n, K[0, 1])
    single = np.zeros(n, dtype=np.int64)  # every correspondence sees the one camera

    def residuals(params: np.ndarray) -> np.ndarray:
        uv, _ = project_with_jacobians(params[None, :3], params[None, 3:], X, intrinsics, skews,
                                       cameras=single, jacobians=False)
        return (uv - x).ravel()

    def jacobian(params: np.ndarray) -> np.ndarray:
        _, J = project_with_jacobians(params[None, :3], params[None, 3:], X, intrinsics, skews,
                                      cameras=single)
        return np.concatenate([J["rotvec"], J["t"]], axis=2).reshape(2 * n, 6)

    before = _rms(reprojection_errors(R, t, X, x, K))
    params0 = np.concatenate([matrix_to_rotvec(nearest_rotation(R)), t])
    with np.errstate(all="ignore"):
        result = least_squares(residuals, params0, jac=jacobian, method="trf", loss=robust_loss(loss),
                               f_scale=float(f_scale),
                               x_scale="jac", max_nfev=200)
    if not np.all(np.isfinite(result.x)):
        return R.copy(), t.copy()
    R_new, t_new = rotvec_to_matrix(result.x[:3]), result.x[3:].copy()
    after = _rms(reprojection_errors(R_new, t_new, X, x, K))
    if not after < before:
        return R.copy(), t.copy()
    return R_new, t_new


__all__ = ["MIN_CORRESPONDENCES", "PnPResult", "dlt_projection_matrices", "pnp_dlt", "pnp_ransac",
           "refine_pnp", "reprojection_errors"]
