"""Two-view relations from a known relative pose: the essential and fundamental matrices.

Camera 2 sits at ``(R, t)`` relative to camera 1 (``X_2 = R X_1 + t``); a point seen at ``x1`` in
image 1 and ``x2`` in image 2 satisfies ``x2^T F x1 = 0``. Used by the synthetic two-view scenes
(exact ground truth) and by the viewer when it draws epipolar lines from a pose.
"""

from __future__ import annotations

import numpy as np

from lab.geometry.rotations import skew


def essential_from_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``E = [t]_x R`` ``(3, 3)`` (Hartley & Zisserman, 2nd ed., result 9.9), not normalized."""
    return skew(np.asarray(t, dtype=np.float64).reshape(3)) @ np.asarray(R, dtype=np.float64)


def fundamental_from_pose(K1: np.ndarray, K2: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The exact ``F = K2^-T [t]_x R K1^-1`` ``(3, 3)``, scaled to unit Frobenius norm (zero stays zero).

    Reference: Hartley & Zisserman (2nd ed.), section 9.6, result 9.9 and eq. (9.2).
    """
    F = np.linalg.inv(K2).T @ essential_from_pose(R, t) @ np.linalg.inv(K1)
    norm = np.linalg.norm(F)
    return F / norm if norm > 0 else F


__all__ = ["essential_from_pose", "fundamental_from_pose"]
