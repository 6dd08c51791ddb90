"""The essential matrix's four relative poses, the cheirality test, and the pose polished on the Sampson
error.

Reference: R. Hartley and A. Zisserman, Multiple View Geometry in Computer Vision (2nd ed., 2004),
sections 9.6.2-9.6.3 (the four solutions and the one in front) and 11.4.3 (the Sampson error).
"""

from __future__ import annotations

import numpy as np

from lab.geometry.homogeneous import to_homogeneous
from lab.geometry.rotations import rotvec_to_matrix, skew
from lab.geometry.triangulation import point_depths, triangulate_dlt
from lab.modules.epipolar._checks import check_matrix
from lab.modules.epipolar.distances import line_terms

#: The names of E's four candidates, in the order of :func:`essential_candidates` (the ``candidate`` control).
CANDIDATE_NAMES = ("R1 t", "R2 t", "R1 -t", "R2 -t")


def essential_candidates(E: np.ndarray) -> np.ndarray:
    """The four ``[R | t]`` of an essential matrix, ``(4, 3, 4)``: ``(R1, t), (R2, t), (R1, -t), (R2, -t)``.

    With ``E = U diag(1, 1, 0) V^T`` (U, V turned into rotations), ``R1 = U W V^T``,
    ``R2 = U W^T V^T``, ``t = u3`` (U's last column), ``W = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]``.
    ``R1`` and ``R2`` differ by a half turn about the baseline, and ``+-t`` by the sign of the
    translation; only one of the four puts the points in front of both cameras (see
    :func:`recover_pose`). Corresponds to ``cv2.decomposeEssentialMat(E)`` (same W and the same four
    poses; which rotation is ``R1`` and the sign of ``t`` follow the signs each SVD picks, so the order of
    OpenCV's may differ). ``U`` and ``V^T`` are made rotations first: with exactly one of determinant -1,
    ``U W V^T`` would be a reflection.

    Reference: H&Z section 9.6.2, result 9.19.
    """
    U, _, Vt = np.linalg.svd(check_matrix(E, "E"))
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R1, R2, t = U @ W @ Vt, U @ W.T @ Vt, U[:, 2]
    return np.stack([np.column_stack([R, s * t]) for s, R in ((1, R1), (1, R2), (-1, R1), (-1, R2))])


def cheirality_counts(candidates: np.ndarray, n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """How many normalized pairs each candidate ``[R | t]`` ``(C, 3, 4)`` puts in front of both cameras (C,).

    Each pair is triangulated (DLT, :func:`lab.geometry.triangulation.triangulate_dlt`) with
    ``P1 = [I | 0]`` and ``P2 = [R | t]``; a point counts when its depth is positive in both.
    """
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    x = np.stack([n1, n2])
    counts = []
    for candidate in candidates:
        P = np.stack([P1, candidate])
        X = triangulate_dlt(P, x)
        finite = np.all(np.isfinite(X), axis=1)
        depth = point_depths(P, np.where(finite[:, None], X, 0.0))
        counts.append(int(np.sum(finite & (depth[0] > 0) & (depth[1] > 0))))
    return np.array(counts)


def tangent_basis(t: np.ndarray) -> np.ndarray:
    """Two unit vectors orthogonal to the unit vector ``t`` and to each other, ``(3, 2)``."""
    helper = np.eye(3)[int(np.argmin(np.abs(t)))]
    a = np.cross(t, helper)
    a /= np.linalg.norm(a)
    return np.column_stack([a, np.cross(t, a)])



def polish_pose(R0: np.ndarray, t0: np.ndarray, x1: np.ndarray, x2: np.ndarray, K1: np.ndarray,
                K2: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the pairs' ``(N, 2)`` Sampson distances to ``F(R, t) = K2^-T [t]_x R K1^-1``.

    Five parameters from the start ``(R0, t0)`` (``|t0| = 1``): ``R = exp([w]_x) R0`` and
    ``t = (t0 + B b) / |t0 + B b|``, ``B`` spanning the plane orthogonal to ``t0``
    (:func:`tangent_basis`); ``scipy.optimize.least_squares`` with at most ``6 iterations`` evaluations,
    kept only if it lowers the cost (and run only with 5 pairs or more). Returns ``R``, ``t`` and the
    Sampson distances ``(N,)`` at the start and at the end.
    """
    from scipy.optimize import least_squares

    B = tangent_basis(t0)
    inverse1, inverse2 = np.linalg.inv(K1), np.linalg.inv(K2)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = t0 + B @ p[3:]
        return rotvec_to_matrix(p[:3]) @ R0, t / np.linalg.norm(t)

    def residuals(p: np.ndarray) -> np.ndarray:
        R, t = unpack(p)
        F = inverse2.T @ skew(t) @ R @ inverse1
        Fx1, Ftx2, algebraic = line_terms(F, x1, x2)
        return algebraic / np.sqrt(Fx1[0] ** 2 + Fx1[1] ** 2 + Ftx2[0] ** 2 + Ftx2[1] ** 2)

    start = residuals(np.zeros(5))
    if iterations > 0 and len(x1) >= 5:
        solution = least_squares(residuals, np.zeros(5), method="lm", max_nfev=int(iterations) * 6,
                                 x_scale=1.0)
        p = solution.x if np.sum(solution.fun**2) <= np.sum(start**2) else np.zeros(5)
    else:
        p = np.zeros(5)
    R, t = unpack(p)
    return R, t, start, residuals(p)


def median_parallax_deg(x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                        R: np.ndarray) -> float:
    """The median angle (degrees) between the two rays of each pair ``(N, 2)``, image 2's turned into camera
    1's frame by ``R^T``: 0 for points at infinity, small when the baseline is small against the depth."""
    ray1 = to_homogeneous(x1) @ np.linalg.inv(K1).T
    ray2 = to_homogeneous(x2) @ np.linalg.inv(K2).T @ R  # R^T (K2^-1 x2): image 2's ray in camera 1's frame
    cosine = np.sum(ray1 * ray2, axis=1) / (np.linalg.norm(ray1, axis=1) * np.linalg.norm(ray2, axis=1))
    return float(np.degrees(np.median(np.arccos(np.clip(cosine, -1.0, 1.0)))))


__all__ = ["CANDIDATE_NAMES", "cheirality_counts", "essential_candidates", "median_parallax_deg",
           "polish_pose", "tangent_basis"]
