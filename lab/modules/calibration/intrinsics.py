"""Zhang's closed-form intrinsics from the homographies, through the image of the absolute conic.

``B = K^-T K^-1`` (up to scale) is symmetric, ``b = (B11, B12, B22, B13, B23, B33)``. The columns
``h1, h2`` of each homography are the images of two orthonormal directions, so
``h1^T B h2 = 0`` and ``h1^T B h1 = h2^T B h2``: with ``h_i^T B h_j = v_ij^T b`` these are two rows
``[v12; v11 - v22]`` of ``V b = 0`` (:func:`conic_constraints`), ``b`` the right singular vector
of ``V`` with the smallest singular value (:func:`absolute_conic`), and ``K`` follows from ``b`` in
closed form (:func:`intrinsics_from_conic`).

Reference: Z. Zhang, "A flexible new technique for camera calibration" (2000), section 3.1 and
appendix B; Hartley & Zisserman (2nd ed.), section 8.8.
"""

from __future__ import annotations

import numpy as np

from lab.core import InvalidValue


def zhang_v(H: np.ndarray, i: int, j: int) -> np.ndarray:
    """Zhang's ``v_ij`` (section 3.1) ``(M, 6)`` of homographies ``(M, 3, 3)``: ``h_i^T B h_j = v_ij^T b``."""
    hi, hj = H[:, :, i], H[:, :, j]
    return np.stack([hi[:, 0] * hj[:, 0], hi[:, 0] * hj[:, 1] + hi[:, 1] * hj[:, 0], hi[:, 1] * hj[:, 1],
                     hi[:, 2] * hj[:, 0] + hi[:, 0] * hj[:, 2], hi[:, 2] * hj[:, 1] + hi[:, 1] * hj[:, 2],
                     hi[:, 2] * hj[:, 2]], axis=-1)


def conic_constraints(H: np.ndarray, *, zero_skew: bool) -> np.ndarray:
    """``V`` ``(2 M (+1), 6)``: two rows per view; ``zero_skew`` adds ``B12 = 0``, heavily weighted.

    Each homography is scaled to unit norm first, so every view weighs the same.
    """
    H = H / np.linalg.norm(H, axis=(1, 2), keepdims=True)
    V = np.concatenate([zhang_v(H, 0, 1), zhang_v(H, 0, 0) - zhang_v(H, 1, 1)], axis=0)
    if zero_skew:
        weight = 1e3 * np.linalg.norm(V, axis=1).max()
        V = np.concatenate([V, [[0.0, weight, 0.0, 0.0, 0.0, 0.0]]], axis=0)
    return V


def absolute_conic(V: np.ndarray) -> np.ndarray:
    """``b`` ``(6,)``: the unit null vector of ``V`` (smallest singular value), signed so ``B11 > 0``."""
    _, singular, Vt = np.linalg.svd(V)
    if singular[-2] <= 1e-12 * singular[0]:
        raise InvalidValue("homographies", "the views do not determine the intrinsics (boards parallel to "
                                           "each other?); tilt the board differently in each photo")
    b = Vt[-1]
    return -b if b[0] < 0 else b


def intrinsics_from_conic(b: np.ndarray, *, zero_skew: bool) -> np.ndarray:
    """``K`` = ``[[alpha, gamma, u0], [0, beta, v0], [0, 0, 1]]`` from ``b`` (Zhang, appendix B)::

        v0 = (B12 B13 - B11 B23) / (B11 B22 - B12^2)
        lambda = B33 - (B13^2 + v0 (B12 B13 - B11 B23)) / B11
        alpha = sqrt(lambda / B11),  beta = sqrt(lambda B11 / (B11 B22 - B12^2))
        gamma = -B12 alpha^2 beta / lambda,  u0 = gamma v0 / beta - B13 alpha^2 / lambda
    """
    B11, B12, B22, B13, B23, B33 = b
    denominator = B11 * B22 - B12 * B12
    if B11 <= 0 or denominator <= 0:
        raise InvalidValue("homographies", _not_positive_definite(f"B11 = {B11:.3g}, B11 B22 - B12^2 = "
                                                                  f"{denominator:.3g}"))
    v0 = (B12 * B13 - B11 * B23) / denominator
    lam = B33 - (B13 * B13 + v0 * (B12 * B13 - B11 * B23)) / B11
    if lam / B11 <= 0:
        raise InvalidValue("homographies", _not_positive_definite(f"lambda / B11 = {lam / B11:.3g}"))
    alpha = np.sqrt(lam / B11)
    beta = np.sqrt(lam * B11 / denominator)
    gamma = 0.0 if zero_skew else -B12 * alpha * alpha * beta / lam
    u0 = gamma * v0 / beta - B13 * alpha * alpha / lam
    return np.array([[alpha, gamma, u0], [0.0, beta, v0], [0.0, 0.0, 1.0]])


def _not_positive_definite(which: str) -> str:
    return (f"the absolute conic these homographies give is not positive definite ({which}), so no camera "
            "matrix K has it: the homographies are not those of a plane seen by one camera (wrong "
            "correspondences, or H maps the other way), or the views are degenerate or too noisy")


__all__ = ["absolute_conic", "conic_constraints", "intrinsics_from_conic", "zhang_v"]
