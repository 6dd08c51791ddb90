"""Each view's pose from its homography and the intrinsics: ``[r1 r2 t] = lambda K^-1 H``.

Reference: Z. Zhang (2000), section 3.1 (eq. 13) and appendix C.
"""

from __future__ import annotations

import numpy as np

from lab.core import InvalidValue
from lab.geometry.rotations import nearest_rotation


def poses_from_homographies(H: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Board-to-camera ``R`` ``(M, 3, 3)`` and ``t`` ``(M, 3)`` (``X_c = R X_board + t``), one per homography.

    ``lambda = 1 / |K^-1 h1|`` (here the mean of ``|K^-1 h1|`` and ``|K^-1 h2|``, which are equal
    without noise), signed so the board lies in front of the camera (``t_z > 0``);
    ``r3 = r1 x r2``. With noise ``[r1 r2 r3]`` is not a rotation: it is replaced by the nearest
    rotation in Frobenius norm, ``U V^T`` of its SVD, with the sign fixed so that det = +1.
    """
    A = np.linalg.solve(K, H)  # K^-1 H, (M, 3, 3)
    norms = 0.5 * (np.linalg.norm(A[:, :, 0], axis=1) + np.linalg.norm(A[:, :, 1], axis=1))
    if np.any(norms <= 0):
        raise InvalidValue("homographies", "a homography has a zero column")
    lam = np.sign(A[:, 2, 2]) / norms
    lam = np.where(lam == 0, 1.0 / norms, lam)
    r1 = lam[:, None] * A[:, :, 0]
    r2 = lam[:, None] * A[:, :, 1]
    t = lam[:, None] * A[:, :, 2]
    Q = np.stack([r1, r2, np.cross(r1, r2)], axis=-1)
    return nearest_rotation(Q), t


__all__ = ["poses_from_homographies"]
