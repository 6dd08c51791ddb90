"""Rotations: axis-angle <-> matrix, the nearest rotation, angles between rotations, SO(3) Jacobians.

Conventions (DESIGN.md section 3): rotations act on column vectors, ``X_c = R X_w + t``; an
axis-angle vector ``w`` (OpenCV's ``rvec``) is the rotation by ``|w|`` radians about ``w / |w|``,
``R = exp([w]_x)`` (Rodrigues' formula). Every function is batched over leading dimensions.

Conversions use :class:`scipy.spatial.transform.Rotation` (they are not the lesson); what is
written here by hand is what students learn: the cross-product matrix, the projection onto SO(3)
through the SVD, and the left Jacobian of SO(3) that makes a Levenberg-Marquardt Jacobian with
axis-angle parameters analytic.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from lab.core.errors import InvalidValue


def _vectors(value: object, name: str, size: int = 3) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim < 1 or array.shape[-1] != size:
        raise InvalidValue(name, f"expected shape (..., {size}), got {array.shape}")
    return array


def _matrices(value: object, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim < 2 or array.shape[-2:] != (3, 3):
        raise InvalidValue(name, f"expected shape (..., 3, 3), got {array.shape}")
    return array


def skew(vectors: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]_x`` with ``[v]_x u = v x u``: ``(..., 3)`` -> ``(..., 3, 3)``.

    Reference: Hartley & Zisserman, Multiple View Geometry (2nd ed.), appendix A4.5.
    """
    v = _vectors(vectors, "vectors")
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotvec_to_matrix(rotvecs: np.ndarray) -> np.ndarray:
    """Axis-angle vectors ``(..., 3)`` to rotation matrices ``(..., 3, 3)`` (``cv2.Rodrigues``)."""
    v = _vectors(rotvecs, "rotvecs")
    return Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix().reshape((*v.shape[:-1], 3, 3))


def matrix_to_rotvec(matrices: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` to axis-angle vectors ``(..., 3)``, angle in [0, pi]
    (``cv2.Rodrigues``)."""
    R = _matrices(matrices, "matrices")
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape((*R.shape[:-2], 3))


def nearest_rotation(matrices: np.ndarray) -> np.ndarray:
    """The rotation closest in Frobenius norm to each ``(..., 3, 3)`` matrix:
    ``U diag(1, 1, det(U V^T)) V^T``.

    Reference: Zhang, "A flexible new technique for camera calibration" (2000), appendix C; the
    determinant correction makes the result a proper rotation (det +1) even for a reflection.
    """
    M = _matrices(matrices, "matrices")
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle in degrees of the relative rotation ``R_a^T R_b`` (geodesic distance on SO(3)), ``(...)``.

    Computed as ``2 atan2(|q_xyz|, |q_w|)`` of the relative quaternion, accurate for tiny angles
    (``arccos((trace - 1) / 2)`` is not).
    """
    A = _matrices(R_a, "R_a")
    B = _matrices(R_b, "R_b")
    relative = np.swapaxes(A, -1, -2) @ B
    shape = relative.shape[:-2]
    rotvec = Rotation.from_matrix(relative.reshape(-1, 3, 3)).as_rotvec()
    return np.degrees(np.linalg.norm(rotvec, axis=-1)).reshape(shape)


def so3_left_jacobian(rotvecs: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3), ``(..., 3)`` -> ``(..., 3, 3)``.

    ``J(w) = I + (1 - cos a) / a^2 [w]_x + (a - sin a) / a^3 [w]_x^2`` with ``a = |w|``, so that
    ``exp([w + dw]_x) ~ exp([J(w) dw]_x) exp([w]_x)`` to first order. Hence for ``Y = R(w) X``:
    ``dY/dw = -[Y]_x J(w)``, the derivative that ``cv2.projectPoints`` reports through
    ``cv2.Rodrigues``' Jacobian. Near ``a = 0`` the Taylor series of the coefficients is used.

    Reference: T. Barfoot, State Estimation for Robotics (2017), section 7.1.5, eq. (7.77);
    G. Gallego and A. Yezzi, "A compact formula for the derivative of a 3-D rotation in
    exponential coordinates", JMIV 51 (2015).
    """
    w = _vectors(rotvecs, "rotvecs")
    a2 = np.sum(w * w, axis=-1)
    a = np.sqrt(a2)
    small = a < 1e-4
    safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5 - a2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    c2 = np.where(small, 1.0 / 6.0 - a2 / 120.0, (safe - np.sin(safe)) / safe**3)
    W = skew(w)
    return np.eye(3) + c1[..., None, None] * W + c2[..., None, None] * (W @ W)


def look_at(eye: ArrayLike, target: ArrayLike,
            up: ArrayLike = (0.0, -1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R, t)`` of OpenCV cameras at ``eye`` looking at ``target``, batched ``(..., 3)``.

    The camera's z axis points at the target and ``up`` is the world direction that appears
    upwards in the image (the camera's y axis, image down, is as close as possible to ``-up``);
    the default suits a world whose y axis points down, as OpenCV's. Returns ``R`` ``(..., 3, 3)``
    and ``t`` ``(..., 3)`` with ``X_c = R X_w + t``.
    """
    eye = _vectors(eye, "eye")
    target = _vectors(target, "target")
    up = _vectors(up, "up")
    z = target - eye
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, np.broadcast_to(up, z.shape))  # x = y cross z with y = -up
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise InvalidValue("up", "the viewing direction is parallel to the up vector")
    x = x / norm
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=-2)
    t = -np.einsum("...ij,...j->...i", R, eye)
    return R, t


__all__ = ["look_at", "matrix_to_rotvec", "nearest_rotation", "rotation_angle_deg", "rotvec_to_matrix",
           "skew", "so3_left_jacobian"]
