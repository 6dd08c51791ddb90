"""The pinhole camera with OpenCV's lens distortion: projection, distortion and its inverse.

Conventions (DESIGN.md section 3): camera frame x right, y down, z forward; world to camera
``X_c = R X_w + t``; pixel (0, 0) is the centre of the top-left pixel;
``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``; distortion ``(k1, k2, p1, p2, k3)`` as in OpenCV.

Normalized coordinates ``x = (X_c / Z_c, Y_c / Z_c)`` are distorted by (Brown-Conrady, OpenCV's
``cv2.projectPoints``)::

    r^2 = x^2 + y^2,   radial = 1 + k1 r^2 + k2 r^4 + k3 r^6
    x_d = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y

and mapped to pixels by ``K``. Every function is batched: points are ``(..., 2)`` or ``(..., 3)``.

References: D. C. Brown, "Decentering distortion of lenses", Photogrammetric Engineering 32(3),
1966; Z. Zhang, "A flexible new technique for camera calibration", TPAMI 22(11), 2000, section
3.3; the OpenCV documentation of ``calib3d`` ("Camera Calibration and 3D Reconstruction").
"""

from __future__ import annotations

import numpy as np

from lab.core.errors import InvalidValue

#: Names of the distortion coefficients, in OpenCV's order.
DISTORTION_NAMES: tuple[str, ...] = ("k1", "k2", "p1", "p2", "k3")


def _last(value: object, name: str, size: int) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim < 1 or array.shape[-1] != size:
        raise InvalidValue(name, f"expected shape (..., {size}), got {array.shape}")
    return array


def as_distortion(dist: object | None) -> np.ndarray:
    """OpenCV distortion coefficients as a ``(5,)`` float64 array (k1, k2, p1, p2, k3).

    Accepts None (no distortion), 4 coefficients (k3 = 0) or 5, in any shape OpenCV uses.
    """
    if dist is None:
        return np.zeros(5)
    d = np.asarray(dist, dtype=np.float64).ravel()
    if d.size == 4:
        d = np.append(d, 0.0)
    if d.size != 5:
        raise InvalidValue("dist", "expected 4 or 5 distortion coefficients (k1, k2, p1, p2[, k3]), "
                                   f"got {d.size}")
    if not np.all(np.isfinite(d)):
        raise InvalidValue("dist", "contains NaN or infinite entries")
    return d


def as_intrinsics(K: object) -> np.ndarray:
    """A ``(3, 3)`` camera matrix, checked: last row (0, 0, 1), non-zero focal lengths."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise InvalidValue("K", f"expected a (3, 3) camera matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)) or not np.allclose(K[2], (0.0, 0.0, 1.0)) \
            or abs(K[1, 0]) > 1e-9 * abs(K[1, 1]):
        raise InvalidValue("K", "a camera matrix is [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    if K[0, 0] == 0.0 or K[1, 1] == 0.0:
        raise InvalidValue("K", "focal lengths must be non-zero")
    return K


def scale_intrinsics(K: np.ndarray, scale: float) -> np.ndarray:
    """``K`` ``(3, 3)`` of the image resized by ``scale`` (a copy): focal lengths and skew times ``scale``,
    the principal point ``c' = (c + 0.5) scale - 0.5`` (pixel centres at integer coordinates, the lab's
    convention: the image's edge ``-0.5`` stays its edge)."""
    out = np.array(K, dtype=np.float64)
    if scale != 1.0:
        out[:2, :2] *= scale
        out[:2, 2] = (out[:2, 2] + 0.5) * scale - 0.5
    return out


def pixels_to_normalized(pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Apply ``K^-1`` to pixels ``(..., 2)`` (skew included): the (distorted) normalized coordinates."""
    K = as_intrinsics(K)
    uv = _last(pixels, "pixels", 2)
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return np.stack([x, y], axis=-1)


def normalized_to_pixels(normalized: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Apply ``K`` to normalized coordinates ``(..., 2)``: ``u = fx x + s y + cx``, ``v = fy y + cy``."""
    K = as_intrinsics(K)
    xy = _last(normalized, "normalized", 2)
    u = K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]
    v = K[1, 1] * xy[..., 1] + K[1, 2]
    return np.stack([u, v], axis=-1)


def distort(normalized: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """OpenCV's lens distortion of normalized coordinates ``(..., 2)`` -> ``(..., 2)`` (module docstring)."""
    xy = _last(normalized, "normalized", 2)
    k1, k2, p1, p2, k3 = as_distortion(dist)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy2 = 2.0 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
    return np.stack([xd, yd], axis=-1)


def distort_components(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, ...]:
    """The fast path of :func:`distort_with_jacobians` for hot loops: coordinates as separate arrays.

    ``x``, ``y`` any matching shapes, ``d`` a ``(5,)`` array (not checked). Returns ``x_d``, ``y_d``
    and the entries ``dxd/dx``, ``dxd/dy = dyd/dx``, ``dyd/dy`` of the (symmetric) 2x2 Jacobian.
    """
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d (r^2)
    xy2 = 2.0 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
    cross = xy2 * dradial + 2.0 * (p1 * x + p2 * y)
    dxx = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    dyy = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, dxx, cross, dyy


def distort_with_jacobians(normalized: np.ndarray,
                           dist: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distorted points and their derivatives, analytic.

    Returns:
        ``x_d`` ``(..., 2)``; ``d x_d / d x`` ``(..., 2, 2)`` (rows: x_d, y_d; columns: x, y);
        ``d x_d / d (k1, k2, p1, p2, k3)`` ``(..., 2, 5)``.

    These are the derivatives ``cv2.projectPoints`` returns in its ``jacobian`` output (chained
    with the pinhole and pose derivatives by the caller).
    """
    xy = _last(normalized, "normalized", 2)
    d = as_distortion(dist)
    x, y = xy[..., 0], xy[..., 1]
    xd, yd, dxx, cross, dyy = distort_components(x, y, d)
    d_point = np.stack([dxx, cross, cross, dyy], axis=-1).reshape((*xy.shape[:-1], 2, 2))
    r2 = x * x + y * y
    r4 = r2 * r2
    xy2 = 2.0 * x * y
    d_dist = np.stack([x * r2, x * r4, xy2, r2 + 2.0 * x * x, x * r4 * r2,
                       y * r2, y * r4, r2 + 2.0 * y * y, xy2, y * r4 * r2],
                      axis=-1).reshape((*xy.shape[:-1], 2, 5))
    return np.stack([xd, yd], axis=-1), d_point, d_dist


def undistort(distorted: np.ndarray, dist: np.ndarray | None, *, max_iterations: int = 20,
              tolerance: float = 1e-14) -> np.ndarray:
    """Invert :func:`distort` on normalized coordinates ``(..., 2)`` by Newton's method.

    Solves ``distort(x) = x_d`` for ``x`` with the analytic 2x2 Jacobian, starting from one
    fixed-point step ``x = x_d / radial(x_d)``; each point stops once its residual is below
    ``tolerance``. Where the Jacobian is singular (beyond the fold of a strong distortion) the
    point keeps its last estimate. Converges in a handful of iterations for real lenses.

    Corresponds to ``cv2.undistortPoints(..., P=None)``, which inverts the same model by the
    fixed-point iteration ``x <- (x_d - tangential(x)) / radial(x)`` (5 iterations by default, so
    OpenCV's answer is less exact where the distortion is strong).
    """
    xd = _last(distorted, "distorted", 2)
    d = as_distortion(dist)
    shape = xd.shape
    target_x = np.ascontiguousarray(xd[..., 0]).ravel()
    target_y = np.ascontiguousarray(xd[..., 1]).ravel()
    if not np.any(d):
        return xd.astype(np.float64, copy=True)
    r2 = target_x * target_x + target_y * target_y
    radial = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))
    radial = np.where(radial > 0.1, radial, 1.0)
    x, y = target_x / radial, target_y / radial
    active = np.arange(len(x))
    for _ in range(max_iterations):
        if len(active) == 0:
            break
        cx, cy = x[active], y[active]
        value_x, value_y, a, b, e = distort_components(cx, cy, d)
        res_x = value_x - target_x[active]
        res_y = value_y - target_y[active]
        det = a * e - b * b
        move = (np.maximum(np.abs(res_x), np.abs(res_y)) > tolerance) & (np.abs(det) > 1e-12)
        safe = np.where(move, det, 1.0)
        x[active] = np.where(move, cx - (e * res_x - b * res_y) / safe, cx)
        y[active] = np.where(move, cy - (a * res_y - b * res_x) / safe, cy)
        active = active[move]
    return np.stack([x, y], axis=-1).reshape(shape)


def transform_points(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World to camera, ``X_c = R X_w + t``: points ``(..., N, 3)``, ``R`` ``(..., 3, 3)``,
    ``t`` ``(..., 3)``."""
    X = _last(points, "points", 3)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    return np.einsum("...ij,...nj->...ni", R, X) + t[..., None, :]


def project(points_camera: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """Pixels of points given in the camera frame ``(..., 3)`` -> ``(..., 2)``: divide by Z, distort, apply K.

    Points on or behind the camera plane (Z <= 0) give non-finite or meaningless pixels; callers
    that may meet them check Z first.
    """
    X = _last(points_camera, "points_camera", 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        normalized = X[..., :2] / X[..., 2:3]
    return normalized_to_pixels(distort(normalized, dist), K)


def project_points(points: np.ndarray, K: np.ndarray, dist: np.ndarray | None, R: np.ndarray,
                   t: np.ndarray) -> np.ndarray:
    """Project world points ``(..., N, 3)`` through cameras ``R`` ``(..., 3, 3)``, ``t`` ``(..., 3)``:
    ``(..., N, 2)``.

    Corresponds to ``cv2.projectPoints`` (which takes ``rvec = matrix_to_rotvec(R)``).
    """
    return project(transform_points(points, R, t), K, dist)


def undistort_pixels(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray | None,
                     K_new: np.ndarray | None = None) -> np.ndarray:
    """Remove lens distortion from pixels ``(..., 2)``; the result is in ``K_new`` (default ``K``).

    Corresponds to ``cv2.undistortPoints(pixels, K, dist, P=K_new)``.
    """
    normalized = undistort(pixels_to_normalized(pixels, K), dist)
    return normalized_to_pixels(normalized, K if K_new is None else K_new)


def undistortion_map(K: np.ndarray, dist: np.ndarray | None, size: tuple[int, int], *,
                     K_new: np.ndarray | None = None, R: np.ndarray | None = None) -> np.ndarray:
    """For every pixel of the undistorted (optionally rotated) image, the pixel to sample in the photo.

    Output pixel ``(u, v)`` -> ray ``(K_new R)^-1 (u, v, 1)`` -> normalized ``(x, y)`` ->
    :func:`distort` -> ``K``. ``size`` is ``(width, height)`` of the output; ``K_new`` defaults
    to ``K`` and ``R`` (a rectifying rotation, for stereo) to the identity. Returns
    ``(height, width, 2)`` float64 source pixels ``(x, y)``, to sample with ``cv2.remap``.

    Corresponds to ``cv2.initUndistortRectifyMap(K, dist, R, K_new, size, cv2.CV_32FC1)``.
    """
    K = as_intrinsics(K)
    K_new = K if K_new is None else as_intrinsics(K_new)
    R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
    width, height = int(size[0]), int(size[1])
    if width < 1 or height < 1:
        raise InvalidValue("size", f"must be a positive (width, height), got {size}")
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K_new @ R).T
    with np.errstate(divide="ignore", invalid="ignore"):
        normalized = rays[..., :2] / rays[..., 2:3]
    return normalized_to_pixels(distort(normalized, dist), K)


def optimal_new_camera_matrix(K: np.ndarray, dist: np.ndarray | None, size: tuple[int, int], *, alpha: float,
                              new_size: tuple[int, int] | None = None) -> np.ndarray:
    """The camera matrix of the undistorted image that keeps ``alpha`` of the photo.

    A 9 x 9 grid of pixels spanning the photo is undistorted (:func:`undistort`); in normalized
    coordinates the *outer* rectangle bounds them all and the *inner* one is the largest
    rectangle bounded by the grid's border columns and rows. ``alpha = 0`` maps the inner
    rectangle onto the new image (only valid pixels), ``alpha = 1`` the outer one (every source
    pixel kept); between, focal lengths and principal point are interpolated linearly. Returns
    ``(3, 3)`` without skew.

    Corresponds to ``cv2.getOptimalNewCameraMatrix(K, dist, size, alpha, new_size)`` (which
    undistorts its grid with 5 fixed-point iterations, so it differs slightly under strong
    distortion).
    """
    if not 0.0 <= float(alpha) <= 1.0:
        raise InvalidValue("alpha", f"must lie in [0, 1], got {alpha}")
    K = as_intrinsics(K)
    width, height = int(size[0]), int(size[1])
    new_width, new_height = (width, height) if new_size is None else (int(new_size[0]), int(new_size[1]))
    steps = 9
    gx, gy = np.meshgrid(np.arange(steps) * (width - 1) / (steps - 1),
                         np.arange(steps) * (height - 1) / (steps - 1))
    points = undistort(pixels_to_normalized(np.stack([gx, gy], axis=-1), K), dist)  # (row, column, 2)
    outer_x0, outer_y0 = points[..., 0].min(), points[..., 1].min()
    outer_x1, outer_y1 = points[..., 0].max(), points[..., 1].max()
    inner_x0, inner_x1 = points[:, 0, 0].max(), points[:, -1, 0].min()
    inner_y0, inner_y1 = points[0, :, 1].max(), points[-1, :, 1].min()
    if inner_x1 <= inner_x0 or inner_y1 <= inner_y0:
        raise InvalidValue("dist", "the distortion is too strong: no valid rectangle remains after "
                                   "undistortion")
    fx0, fy0 = (new_width - 1) / (inner_x1 - inner_x0), (new_height - 1) / (inner_y1 - inner_y0)
    fx1, fy1 = (new_width - 1) / (outer_x1 - outer_x0), (new_height - 1) / (outer_y1 - outer_y0)
    cx0, cy0 = -fx0 * inner_x0, -fy0 * inner_y0
    cx1, cy1 = -fx1 * outer_x0, -fy1 * outer_y0
    a = float(alpha)
    return np.array([[fx0 * (1 - a) + fx1 * a, 0.0, cx0 * (1 - a) + cx1 * a],
                     [0.0, fy0 * (1 - a) + fy1 * a, cy0 * (1 - a) + cy1 * a],
                     [0.0, 0.0, 1.0]])


__all__ = ["DISTORTION_NAMES", "as_distortion", "as_intrinsics", "distort", "distort_components",
           "distort_with_jacobians", "normalized_to_pixels", "optimal_new_camera_matrix",
           "pixels_to_normalized", "project", "project_points", "scale_intrinsics", "transform_points",
           "undistort", "undistort_pixels", "undistortion_map"]
