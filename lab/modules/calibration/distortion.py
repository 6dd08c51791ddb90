"""Radial distortion ``k1, k2`` by linear least squares, the intrinsics and poses held fixed.

Reference: Z. Zhang (2000), section 3.3, eq. (13).
"""

from __future__ import annotations

import numpy as np

from lab.core import InvalidValue
from lab.modules.calibration.observations import Observations


def linear_radial_distortion(seen: Observations, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(k1, k2, 0, 0, 0)`` (OpenCV's order) that fit the observed corners, ``K`` and the poses ``R``, ``t``.

    With ``(u, v)`` the ideal (undistorted) projection of a board corner, ``(x, y)`` its ideal
    normalized coordinates and ``r^2 = x^2 + y^2``, the observed ``(u_d, v_d)`` satisfy::

        u_d - u = (u - u0) (k1 r^2 + k2 r^4)
        v_d - v = (v - v0) (k1 r^2 + k2 r^4)

    two linear equations per corner in ``(k1, k2)``, stacked over all corners and solved by least
    squares (``D k = d``).
    """
    camera = np.einsum("nij,nj->ni", R[seen.position], seen.points) + t[seen.position]
    if np.any(camera[:, 2] <= 0):
        raise InvalidValue("R_init", "some board corners lie behind the camera with these poses")
    x = camera[:, :2] / camera[:, 2:3]
    r2 = np.sum(x * x, axis=1)
    ideal = x @ K[:2, :2].T + K[:2, 2]
    centred = ideal - K[:2, 2]
    D = np.stack([centred * r2[:, None], centred * (r2 * r2)[:, None]], axis=-1).reshape(-1, 2)
    d = (seen.pixels - ideal).reshape(-1)
    k, *_ = np.linalg.lstsq(D, d, rcond=None)
    return np.array([k[0], k[1], 0.0, 0.0, 0.0])


__all__ = ["linear_radial_distortion"]
