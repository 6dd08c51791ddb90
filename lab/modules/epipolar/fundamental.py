"""The fundamental matrix by the (normalized) 8-point algorithm, batched: what the lesson covers.

Reference: R. Hartley and A. Zisserman, Multiple View Geometry in Computer Vision (2nd ed., 2004),
section 11.1 and algorithm 11.1; R. Hartley, "In defense of the eight-point algorithm", TPAMI 19(6), 1997.
"""

from __future__ import annotations

from typing import cast

import numpy as np

from lab.geometry.homogeneous import hartley_normalization


def enforce_rank2(F: np.ndarray) -> np.ndarray:
    """The rank-2 matrix nearest in Frobenius norm: zero the smallest singular value, ``(..., 3, 3)``.

    Every fundamental matrix is singular (its null vectors are the epipoles); the linear solution
    of the 8-point algorithm is not, and its epipolar lines would not meet in one point.
    Reference: H&Z section 11.1.1 (the singularity constraint).
    """
    U, singular, Vt = np.linalg.svd(np.asarray(F, dtype=np.float64))
    singular = singular.copy()
    singular[..., 2] = 0.0
    return (U * singular[..., None, :]) @ Vt


def null_vector(A: np.ndarray) -> np.ndarray:
    """Unit ``f`` minimizing ``|A f|`` for each ``(..., N, 9)`` system: its (least-squares) null vector.

    With at most 8 rows (a minimal sample) it is exact: the last column of the complete QR
    factorization of ``A^T`` is orthogonal to every row (4x faster than an SVD, which matters inside
    RANSAC). With more rows, the right singular vector of the smallest singular value, after a QR
    reduction of ``A`` to 9 x 9 (same singular values, without squaring the condition number as
    ``A^T A`` would).
    """
    if A.shape[-2] <= 8:
        Q, _ = np.linalg.qr(np.swapaxes(A, -1, -2), mode="complete")
        return Q[..., :, -1]
    if A.shape[-2] > 9:
        A = cast(np.ndarray, np.linalg.qr(A, mode="r"))  # the R factor only: same singular values
    return np.linalg.svd(A)[2][..., -1, :]


def design_matrix(n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """The rows ``[u2 u1, u2 v1, u2, v2 u1, v2 v1, v2, u1, v1, 1]`` of ``A f = 0``, ``(..., N, 9)``.

    ``x2^T F x1 = 0`` is linear in the entries of F (``f``, row-major): one row per correspondence.
    """
    u1, v1 = n1[..., 0], n1[..., 1]
    u2, v2 = n2[..., 0], n2[..., 1]
    return np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=-1)


def eight_point(x1: np.ndarray, x2: np.ndarray, *, normalize: bool = True) -> np.ndarray:
    """The 8-point algorithm, batched: ``(..., N, 2)`` pairs -> ``(..., 3, 3)`` rank-2 F, unit norm.

    See :func:`estimate_fundamental_8point` (the step, with input checks). No degeneracy checks
    here: RANSAC calls it on thousands of random samples at once.
    """
    x1 = np.asarray(x1, dtype=np.float64)
    x2 = np.asarray(x2, dtype=np.float64)
    if normalize:
        T1, x1 = hartley_normalization(x1)
        T2, x2 = hartley_normalization(x2)
    f = null_vector(design_matrix(x1, x2))  # x2^T F x1 = 0 is linear in F: one row per match
    F = enforce_rank2(f.reshape((*f.shape[:-1], 3, 3)))
    if normalize:
        F = np.swapaxes(T2, -1, -2) @ F @ T1
    return F / np.linalg.norm(F, axis=(-2, -1), keepdims=True)


def numerical_rank(M: np.ndarray) -> int:
    singular = np.linalg.svd(M, compute_uv=False)
    return int(np.sum(singular > 1e-10 * singular[0]))


__all__ = ["design_matrix", "eight_point", "enforce_rank2", "null_vector", "numerical_rank"]
