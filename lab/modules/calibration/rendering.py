"""Rendering a checkerboard photo with exact anti-aliasing, for the synthetic dataset.

Each pixel's ray is undistorted once per camera (:class:`PixelRays`), met with the board plane in
every view, and the printed pattern is averaged exactly over the pixel's footprint on the board
(:func:`box_fractions`, the box filter that supersampling approximates). Corner noise moves the
pattern smoothly under the pixels (:func:`board_displacements`, :func:`interpolate_grid`), so a
corner appears displaced while the truth keeps its exact projection.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lab.core import InvalidValue
from lab.geometry.camera import distort_components, pixels_to_normalized, project_points, undistort
from lab.modules.calibration.board import BACKGROUND, Checkerboard

_PALETTE_GRAY = np.array([0.06, 0.94, 0.4])  # black, white, background
_PALETTE_RGB = np.array([[0.07, 0.06, 0.06], [0.95, 0.93, 0.88], [0.30, 0.42, 0.55]])


class PixelRays:
    """Undistorted normalized coordinates of every pixel centre of one camera, shared by all its views.

    ``x``, ``y`` ``(H, W)`` and their derivatives ``x_u = dx/du``, ``x_v``, ``y_u``, ``y_v`` (inverse
    of the distortion's Jacobian times ``K^-1``), which give each pixel's footprint.
    """

    def __init__(self, K: np.ndarray, dist: np.ndarray, width: int, height: int) -> None:
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        distorted = pixels_to_normalized(np.stack([u, v], axis=-1), K)
        normalized = undistort(distorted, dist)
        x, y = normalized[..., 0], normalized[..., 1]
        xd, yd, a, b, d = distort_components(x, y, dist)  # Jacobian [[a, b], [b, d]]
        det = a * d - b * b
        if not np.all(np.isfinite(normalized)) or max(np.max(np.abs(xd - distorted[..., 0])),
                                                      np.max(np.abs(yd - distorted[..., 1]))) > 1e-9 \
                or np.min(det) <= 0:
            raise InvalidValue("k1", "this distortion folds over inside the image (the lens model is not "
                                     "invertible there); use smaller distortion coefficients")
        # d(x, y)/d(u, v) = Jd^-1 K^-1[:2, :2], with K^-1[:2, :2] = [[1/fx, -s/(fx fy)], [0, 1/fy]]
        k00, k01, k11 = 1.0 / K[0, 0], -K[0, 1] / (K[0, 0] * K[1, 1]), 1.0 / K[1, 1]
        i00, i01, i11 = d / det, -b / det, a / det

        def as32(value: np.ndarray) -> np.ndarray:
            # float32 for the per-view tracing: board coordinates to ~1e-7 of their size, far below a pixel
            return np.ascontiguousarray(value, dtype=np.float32)

        self.x, self.y = as32(x), as32(y)
        self.x_u, self.x_v = as32(i00 * k00), as32(i00 * k01 + i01 * k11)
        self.y_u, self.y_v = as32(i01 * k00), as32(i01 * k01 + i11 * k11)
        self.width = width
        self.height = height


def board_displacements(board: Checkerboard, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
                        displacement: np.ndarray) -> np.ndarray:
    """Image displacements ``(N, 2)`` of the corners as board-plane displacements ``(rows, columns, 2)``.

    ``delta_b_i = J_i^-1 d_i`` with ``J_i`` = d(pixel)/d(board X, Y) at corner ``i`` (central
    differences, all corners at once).
    """
    points = board.object_points()
    h = 1e-6 * board.square_size
    offsets = np.array([[h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0]])
    shifted = project_points(points[None] + offsets[:, None], K, dist, R, t)  # (4, N, 2)
    # (N, 2, 2)
    J = np.stack([(shifted[0] - shifted[1]) / (2 * h), (shifted[2] - shifted[3]) / (2 * h)], axis=-1)
    board_shift = np.linalg.solve(J, displacement[..., None])[..., 0]
    return board_shift.reshape(board.rows, board.columns, 2)


def interpolate_grid(board: Checkerboard, values: np.ndarray, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``values`` ``(rows, columns, 2)`` given at the inner corners, at board
    coordinates ``(X, Y)`` (clamped to the corner grid outside it): ``X.shape + (2,)``.

    Each grid cell's bilinear polynomial ``a + b u + c v + d u v`` is tabulated once, so every point
    needs one gather."""
    c, r = board.columns, board.rows
    v00, v01, v10, v11 = values[:-1, :-1], values[:-1, 1:], values[1:, :-1], values[1:, 1:]
    table = np.concatenate([v00, v01 - v00, v10 - v00, v11 - v01 - v10 + v00], axis=-1).reshape(-1, 8)
    gx = np.clip(X * (1.0 / board.square_size), 0.0, c - 1)
    gy = np.clip(Y * (1.0 / board.square_size), 0.0, r - 1)
    i0 = np.minimum(gx.astype(np.intp), c - 2)
    j0 = np.minimum(gy.astype(np.intp), r - 2)
    u = (gx - i0)[..., None]
    v = (gy - j0)[..., None]
    coefficients = table[j0 * (c - 1) + i0]
    return (coefficients[..., 0:2] + u * coefficients[..., 2:4]
            + v * (coefficients[..., 4:6] + u * coefficients[..., 6:8]))


def box_fractions(board: Checkerboard, X: np.ndarray, Y: np.ndarray, reach_x: np.ndarray,
                  reach_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact box-filtered pattern: fractions of black and of paper in ``[X +- reach_x] x [Y +- reach_y]``.

    The pattern is separable: with ``rect`` the indicator of the squares' span, ``c = (-1)^floor(X/s)``
    and ``paper`` the paper's span, black = ``(rect(X) rect(Y) + (rect c)(X) (rect c)(Y)) / 2`` and
    paper = ``paper(X) paper(Y)``. The mean of each 1-D factor over an interval is the difference
    of its integral (piecewise linear: ``clip`` for an indicator, a triangle wave for ``c``) at the
    interval's ends, so the mean over the box is exact. White is paper minus black; the rest is
    background.
    """
    s = board.square_size
    lo_x, hi_x = -s, board.columns * s
    lo_y, hi_y = -s, board.rows * s

    def triangle(u: np.ndarray) -> np.ndarray:  # integral of (-1)^floor(x / s) from 0 to u
        return s * (1.0 - np.abs(np.mod(u * (1.0 / s), 2.0) - 1.0))

    def mean(integral: Callable[[np.ndarray], np.ndarray], centre: np.ndarray,
             reach: np.ndarray) -> np.ndarray:
        return (integral(centre + reach) - integral(centre - reach)) / (2.0 * reach)

    rect_x = mean(lambda u: np.clip(u, lo_x, hi_x), X, reach_x)
    rect_y = mean(lambda u: np.clip(u, lo_y, hi_y), Y, reach_y)
    alt_x = mean(lambda u: triangle(np.clip(u, lo_x, hi_x)), X, reach_x)
    alt_y = mean(lambda u: triangle(np.clip(u, lo_y, hi_y)), Y, reach_y)
    paper = mean(lambda u: np.clip(u, lo_x - s, hi_x + s), X, reach_x) \
        * mean(lambda u: np.clip(u, lo_y - s, hi_y + s), Y, reach_y)
    return 0.5 * (rect_x * rect_y + alt_x * alt_y), paper


def render_view(board: Checkerboard, rays: PixelRays, K: np.ndarray, dist: np.ndarray, R: np.ndarray,
                t: np.ndarray, board_shift: np.ndarray, *, color: bool) -> np.ndarray:
    """One view: ``(H, W)`` or ``(H, W, 3)`` float64 in [0, 1], anti-aliased (see the synthetic dataset).

    Each pixel's ray meets the board at ``(X, Y)`` (the inverse of the board-to-normalized
    homography ``[r1 r2 t]``); the pixel's footprint on the board, a small parallelogram given
    by the derivative of that map, is replaced by its bounding box, over which the pattern is
    averaged exactly (:func:`box_fractions`). This is the box filter that supersampling
    approximates (4 x 4 samples would quantize an edge parallel to the pixel grid to a quarter
    pixel), and a symmetric blur, so it moves no edge and no corner. Only the bounding box of the
    paper (plus 3 px) is traced; the rest is background.
    """
    palette = _PALETTE_RGB if color else _PALETTE_GRAY
    out = np.empty((rays.height, rays.width, *palette.shape[1:]))
    out[...] = palette[BACKGROUND]
    outline = project_points(board.paper_outline(), K, dist, R, t)
    c0, r0 = np.maximum(np.floor(outline.min(axis=0) - 3).astype(int), 0)
    c1, r1 = np.minimum(np.ceil(outline.max(axis=0) + 4).astype(int), (rays.width, rays.height))
    if c1 <= c0 or r1 <= r0:
        return out
    # normalized -> board coordinates, homogeneous
    T = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t])).astype(np.float32)
    crop = (slice(r0, r1), slice(c0, c1))
    x, y = rays.x[crop], rays.y[crop]
    x_u, x_v, y_u, y_v = rays.x_u[crop], rays.x_v[crop], rays.y_u[crop], rays.y_v[crop]
    p_w = T[2, 0] * x + T[2, 1] * y + T[2, 2]
    front = p_w > 0
    inv_w = 1.0 / np.where(front, p_w, 1.0)
    X = (T[0, 0] * x + T[0, 1] * y + T[0, 2]) * inv_w
    Y = (T[1, 0] * x + T[1, 1] * y + T[1, 2]) * inv_w
    # d(X, Y)/d(u, v) = (d p_xy - (X, Y) d p_w) / p_w, with d p = T[:, :2] d(x, y)/d(u, v)
    w_u = T[2, 0] * x_u + T[2, 1] * y_u
    w_v = T[2, 0] * x_v + T[2, 1] * y_v
    X_u = (T[0, 0] * x_u + T[0, 1] * y_u - X * w_u) * inv_w
    X_v = (T[0, 0] * x_v + T[0, 1] * y_v - X * w_v) * inv_w
    Y_u = (T[1, 0] * x_u + T[1, 1] * y_u - Y * w_u) * inv_w
    Y_v = (T[1, 0] * x_v + T[1, 1] * y_v - Y * w_v) * inv_w
    tiny = np.float32(1e-9 * board.square_size)
    reach_x = 0.5 * (np.abs(X_u) + np.abs(X_v)) + tiny
    reach_y = 0.5 * (np.abs(Y_u) + np.abs(Y_v)) + tiny
    if np.any(board_shift):
        shift = interpolate_grid(board, board_shift, X, Y)
        X = X - shift[..., 0]
        Y = Y - shift[..., 1]
    black, paper = box_fractions(board, X, Y, reach_x, reach_y)
    black = np.where(front, black, 0.0)
    paper = np.where(front, paper, 0.0)
    weights = (black, paper - black, 1.0 - paper)
    if color:
        out[crop] = sum(w[..., None] * palette[k] for k, w in enumerate(weights))
    else:
        out[crop] = sum(w * palette[k] for k, w in enumerate(weights))
    return out


__all__ = ["PixelRays", "board_displacements", "box_fractions", "interpolate_grid", "render_view"]
