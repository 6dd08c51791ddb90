"""Triangulation: 3D points from their images in two or more views with known projection matrices.

A view is a ``3 x 4`` projection matrix ``P = K [R | t]`` (world to pixels, no lens distortion:
undistort the observations first). Observations are pixels ``(V, N, 2)``: view ``v`` sees point
``n`` at ``x[v, n]``; an optional mask ``(V, N)`` says which views see which point.

* :func:`triangulate_dlt` - the linear (DLT) solution, the null vector of a ``2V x 4`` system per
  point (H&Z section 12.2); with two views it is ``cv2.triangulatePoints``.
* :func:`refine_points` - Levenberg-Marquardt on each point's reprojection error (H&Z section 12.5's
  maximum-likelihood criterion with the cameras held fixed), all points at once.
* :func:`reprojection_residuals`, :func:`point_depths` - the error the refinement minimizes and the
  depth of each point in each view (positive in front, the cheirality test).
"""

from __future__ import annotations

import numpy as np

from lab.core.errors import InvalidValue


def _projections(value: object) -> np.ndarray:
    P = np.asarray(value, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (3, 4) or len(P) < 2:
        raise InvalidValue("projections", f"expected (V >= 2, 3, 4) projection matrices, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise InvalidValue("projections", "contains NaN or infinite entries")
    return P


def _observations(value: object, views: int) -> np.ndarray:
    x = np.asarray(value, dtype=np.float64)
    if x.ndim != 3 or x.shape[0] != views or x.shape[2] != 2:
        raise InvalidValue("points2d", f"expected ({views}, N, 2) pixels, got shape {x.shape}")
    return x


def _mask(mask: object | None, shape: tuple[int, int]) -> np.ndarray:
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask, dtype=bool)
    if m.shape != shape:
        raise InvalidValue("mask", f"expected shape {shape}, got {m.shape}")
    if np.any(m.sum(axis=0) < 2):
        raise InvalidValue("mask", "every point must be seen in at least two views")
    return m


def projection_matrix(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``P = K [R | t]``, batched: ``K``, ``R`` ``(..., 3, 3)`` and ``t`` ``(..., 3)`` -> ``(..., 3, 4)``."""
    K = np.asarray(K, dtype=np.float64)
    Rt = np.concatenate([np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)[..., None]],
                        axis=-1)
    return K @ Rt


def triangulate_dlt(projections: np.ndarray, points2d: np.ndarray,
                    mask: np.ndarray | None = None) -> np.ndarray:
    """Linear triangulation: for each point the null vector of the stacked DLT rows of every view.

    Each view ``v`` with ``P = (p1; p2; p3)`` (rows) seeing the point at ``(x, y)`` gives two rows
    ``x p3 - p1`` and ``y p3 - p2`` of ``A X = 0`` (``x cross P X = 0``); ``X`` is the right singular
    vector of ``A`` with the smallest singular value, then de-homogenized. Views that do not see a
    point contribute zero rows. Solved for all points by one batched SVD, in the given pixel
    coordinates (as OpenCV does; the result is not invariant to the image frames, which is why
    :func:`refine_points` follows).

    Args:
        projections: ``(V, 3, 4)`` projection matrices.
        points2d: ``(V, N, 2)`` observed pixels.
        mask: ``(V, N)`` bool, which views see which point (default: all).

    Returns ``(N, 3)`` points; a point whose homogeneous coordinate is 0 (at infinity) is returned
    as ``inf`` in the direction found. Two views give what ``cv2.triangulatePoints(P1, P2, x1.T,
    x2.T)`` gives, de-homogenized.

    Reference: Hartley & Zisserman, Multiple View Geometry (2nd ed.), section 12.2.
    """
    P = _projections(projections)
    x = _observations(points2d, len(P))
    m = _mask(mask, x.shape[:2]).astype(np.float64)
    rows_x = x[..., 0:1] * P[:, None, 2, :] - P[:, None, 0, :]  # (V, N, 4)
    rows_y = x[..., 1:2] * P[:, None, 2, :] - P[:, None, 1, :]
    A = np.concatenate([rows_x * m[..., None], rows_y * m[..., None]], axis=0)  # (2V, N, 4)
    _, _, Vt = np.linalg.svd(np.swapaxes(A, 0, 1))  # (N, 4, 4)
    X = Vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:]


def point_depths(projections: np.ndarray, points3d: np.ndarray) -> np.ndarray:
    """Depth of each point in each view, ``(V, N)``: positive in front of the camera.

    For ``P = K [R | t]`` with ``det(K[:, :3]) > 0`` (any real camera) the third coordinate of
    ``P X`` is the depth ``Z_c`` times ``K[2, 2]``; the sign of ``det(P[:, :3])`` fixes it for any P
    (H&Z section 6.2.3, eq. (6.15)). Points behind a camera violate cheirality.
    """
    P = _projections(projections)
    X = np.asarray(points3d, dtype=np.float64)
    w = np.einsum("vj,nj->vn", P[:, 2, :3], X) + P[:, 2, 3][:, None]
    M = P[:, :, :3]
    scale = np.sign(np.linalg.det(M)) / np.linalg.norm(M[:, 2], axis=1)
    return w * scale[:, None]


def reprojection_residuals(projections: np.ndarray, points3d: np.ndarray, points2d: np.ndarray) -> np.ndarray:
    """Projected minus observed pixels, ``(V, N, 2)``: ``pi(P_v X_n) - x_{v n}``."""
    P = _projections(projections)
    x = _observations(points2d, len(P))
    X = np.asarray(points3d, dtype=np.float64)
    if X.shape != (x.shape[1], 3):
        raise InvalidValue("points3d", f"expected ({x.shape[1]}, 3), got {X.shape}")
    projected = np.einsum("vij,nj->vni", P[:, :, :3], X) + P[:, None, :, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return projected[..., :2] / projected[..., 2:] - x


def refine_points(projections: np.ndarray, points2d: np.ndarray, points3d: np.ndarray,
                  mask: np.ndarray | None = None, *, iterations: int = 10,
                  tolerance: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Minimize each point's reprojection error over its position, cameras fixed (Levenberg-Marquardt).

    Residual of view ``v``: ``r_v = (u, v)(P_v X) - x_v`` with ``(u, v)(p) = (p1 / p3, p2 / p3)``;
    its Jacobian is ``(1 / p3) [P_1 - u P_3; P_2 - v P_3]`` (the first three columns of ``P``'s
    rows). Each point solves its own ``3 x 3`` damped normal equations ``(J^T J + lambda I) dX =
    -J^T r``, all points at once; a step that lowers a point's error is kept and its ``lambda``
    shrinks 10x, one that does not is undone and its ``lambda`` grows 10x. Points stop when their
    step is below ``tolerance`` times their distance from the origin.

    Args:
        projections: ``(V, 3, 4)``.
        points2d: ``(V, N, 2)`` observations.
        points3d: ``(N, 3)`` starting points (the DLT's).
        mask: ``(V, N)`` which views see which point (default: all).
        iterations: most iterations.
        tolerance: relative step size that stops a point.

    Returns the refined points ``(N, 3)`` and the RMS reprojection error (px, over all
    observations) before the first and after every iteration, ``(iterations run + 1,)``.

    No single OpenCV call: with two views, triangulating the pairs that ``cv2.correctMatches`` (the
    optimal correction of H&Z section 12.5, Hartley and Sturm's polynomial) moved onto the epipolar
    constraint reaches the same minimum by another route (the tests compare them); bundle
    adjustment refines points and cameras together.

    Reference: Hartley & Zisserman (2nd ed.), sections 12.5 (the maximum-likelihood criterion)
    and A6.2 (Levenberg-Marquardt).
    """
    P = _projections(projections)
    x = _observations(points2d, len(P))
    m = _mask(mask, x.shape[:2]).astype(np.float64)
    X = np.array(points3d, dtype=np.float64, copy=True)
    if X.shape != (x.shape[1], 3):
        raise InvalidValue("points3d", f"expected ({x.shape[1]}, 3), got {X.shape}")
    count = max(float(m.sum()), 1.0)

    def evaluate(points: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = np.einsum("vij,nj->vni", P[:, :, :3], points) + P[:, None, :, 3]  # (V, n, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = p[..., :2] / p[..., 2:]
        r = (uv - x[:, index]) * m[:, index, None]
        return r, np.sum(r * r, axis=(0, 2)), p

    r, cost, p = evaluate(X, np.arange(len(X)))
    cost = np.where(np.isfinite(cost), cost, np.inf)
    history = [float(np.sqrt(np.sum(cost[np.isfinite(cost)]) / count))]
    damping = np.full(len(X), 1e-3)
    active = np.isfinite(cost) & np.all(np.isfinite(X), axis=1)
    for _ in range(int(iterations)):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        pa, ra, ma = p[:, idx], r[:, idx], m[:, idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_w = ma / pa[..., 2]
            J = np.stack([(P[:, None, 0, :3] - (pa[..., 0] / pa[..., 2])[..., None] * P[:, None, 2, :3]),
                          (P[:, None, 1, :3] - (pa[..., 1] / pa[..., 2])[..., None] * P[:, None, 2, :3])],
                         axis=2) * inv_w[..., None, None]  # (V, n, 2, 3)
        JtJ = np.einsum("vnki,vnkj->nij", J, J)
        Jtr = np.einsum("vnki,vnk->ni", J, ra)
        diagonal = np.einsum("nii->ni", JtJ)
        system = JtJ + (damping[idx][:, None] * np.maximum(diagonal, 1e-12))[:, :, None] * np.eye(3)
        solvable = np.isfinite(system).all(axis=(1, 2)) & (np.abs(np.linalg.det(system)) > 0)
        step = np.zeros((len(idx), 3))
        if solvable.any():
            step[solvable] = -np.linalg.solve(system[solvable], Jtr[solvable][..., None])[..., 0]
        candidate = X[idx] + step
        r_new, cost_new, p_new = evaluate(candidate, idx)
        better = solvable & np.isfinite(cost_new) & (cost_new < cost[idx])
        keep = idx[better]
        X[keep] = candidate[better]
        cost[keep] = cost_new[better]
        r[:, keep] = r_new[:, better]
        p[:, keep] = p_new[:, better]
        damping[keep] = np.maximum(damping[keep] / 10.0, 1e-12)
        damping[idx[~better]] *= 10.0
        small = np.linalg.norm(step, axis=1) <= tolerance * np.maximum(np.linalg.norm(X[idx], axis=1), 1.0)
        stop = small | (damping[idx] > 1e12) | ~solvable
        active[idx[stop]] = False
        history.append(float(np.sqrt(np.sum(cost[np.isfinite(cost)]) / count)))
    return X, np.array(history)


__all__ = ["point_depths", "projection_matrix", "refine_points", "reprojection_residuals", "triangulate_dlt"]
