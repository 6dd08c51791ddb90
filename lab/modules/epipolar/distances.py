"""How far pairs of pixels are from satisfying ``x2^T F x1 = 0``: Sampson and point-to-line distances,
batched.

Reference: R. Hartley and A. Zisserman, Multiple View Geometry in Computer Vision (2nd ed., 2004),
section 11.4.3.
"""

from __future__ import annotations

import numpy as np

from lab.geometry.homogeneous import to_homogeneous


def line_terms(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``F x1`` and ``F^T x2`` ``(..., 3, N)`` and the algebraic residuals ``x2^T F x1`` ``(..., N)``.

    One matrix product for all the matrices of a batch (``(B 3, 3) x (3, N)``): RANSAC scores
    hundreds of hypotheses against every match at once.
    """
    F = np.asarray(F, dtype=np.float64)
    h1, h2 = to_homogeneous(x1), to_homogeneous(x2)
    lead = F.shape[:-2]
    Fx1 = (F.reshape(-1, 3) @ h1.T).reshape((*lead, 3, len(h1)))  # lines in image 2, a column per point
    Ftx2 = (np.swapaxes(F, -1, -2).reshape(-1, 3) @ h2.T).reshape((*lead, 3, len(h2)))  # lines in image 1
    algebraic = np.sum(h2.T * Fx1, axis=-2)
    return Fx1, Ftx2, algebraic


def sampson_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric error of each pair, in pixels.

    ``d = |x2^T F x1| / sqrt((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2)``:
    the distance in the joint image space ``(x1, y1, x2, y2)`` from the pair to the variety
    ``x2^T F x1 = 0``, linearized (Sampson 1982): about the smallest total move of the two points
    that makes them consistent with F. Batched: ``F`` ``(..., 3, 3)`` against ``x1``, ``x2``
    ``(N, 2)`` gives ``(..., N)``. ``cv2.sampsonDistance(x1, x2, F)`` returns its square.

    Reference: H&Z section 11.4.3, eq. (11.9).
    """
    Fx1, Ftx2, algebraic = line_terms(F, x1, x2)
    gradient = Fx1[..., 0, :] ** 2 + Fx1[..., 1, :] ** 2 + Ftx2[..., 0, :] ** 2 + Ftx2[..., 1, :] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(algebraic) / np.sqrt(gradient)


def epipolar_distances(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-line distances (px), ``(..., N)`` each: ``x1`` from ``F^T x2``, ``x2`` from ``F x1``."""
    Fx1, Ftx2, algebraic = line_terms(F, x1, x2)
    algebraic = np.abs(algebraic)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (algebraic / np.hypot(Ftx2[..., 0, :], Ftx2[..., 1, :]),
                algebraic / np.hypot(Fx1[..., 0, :], Fx1[..., 1, :]))


def symmetric_epipolar_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """``sqrt(d(x1, F^T x2)^2 + d(x2, F x1)^2)`` in pixels, ``(..., N)``: both point-to-line distances.

    Reference: H&Z section 11.4.3, eq. (11.10) (whose sum over points is this squared).
    """
    d1, d2 = epipolar_distances(F, x1, x2)
    return np.sqrt(d1 * d1 + d2 * d2)


__all__ = ["epipolar_distances", "line_terms", "sampson_distance", "symmetric_epipolar_distance"]
