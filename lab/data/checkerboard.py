"""Checkerboard datasets for camera calibration: a synthetic generator with exact truth, and a folder loader.

The board (:class:`Checkerboard`) has ``columns x rows`` inner corners; corner ``k = r * columns + c``
lies at ``(c * square_size, r * square_size, 0)`` in the board frame, which is the order in which
``cv2.findChessboardCorners`` returns them (row by row). The square between corners 0, 1,
``columns`` and ``columns + 1`` is black, as in OpenCV's sample photos; for boards whose corner
counts differ in parity (9 x 6) that colour fixes which end of the board is corner 0.

The synthetic generator (:func:`synthetic`) renders the board printed on white paper, seen by a
camera with known ``K``, OpenCV distortion and poses, anti-aliased exactly, slightly blurred, with
corners displaced by a controlled amount of noise and a little pixel noise; its truth holds the exact
``K``, distortion, poses and projections of every corner.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

from lab.core import Image, ImageSet, InvalidValue, Loaded, Mesh, Points2D, Range
from lab.core.budgets import check_dataset_pixels
from lab.geometry.camera import (as_distortion, distort_components, pixels_to_normalized, project_points,
                                 undistort)
from lab.geometry.rotations import rotvec_to_matrix

#: Label values of the printed pattern (see :meth:`Checkerboard.labels`).
BLACK, WHITE, BACKGROUND = 0, 1, 2


@dataclass(frozen=True)
class Checkerboard:
    """A chessboard calibration target.

    ``columns`` inner corners per row, ``rows`` inner corners per column (OpenCV's ``patternSize``
    is ``(columns, rows)``), squares of ``square_size`` metres. The printed pattern has
    ``(columns + 1) x (rows + 1)`` squares, spanning ``[-s, columns * s] x [-s, rows * s]``.
    """

    columns: int = 9
    rows: int = 6
    square_size: float = 0.025

    def __post_init__(self) -> None:
        for name in ("columns", "rows"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 2:
                raise InvalidValue(name, f"a board needs an integer of at least 2 inner corners, got {value!r}")
            object.__setattr__(self, name, int(value))
        size = self.square_size
        if isinstance(size, bool) or not isinstance(size, (int, float, np.integer, np.floating)) \
                or not np.isfinite(size) or size <= 0:
            raise InvalidValue("square_size", f"must be a positive number of metres, got {size!r}")
        object.__setattr__(self, "square_size", float(size))

    @property
    def pattern_size(self) -> tuple[int, int]:
        """``(columns, rows)``, OpenCV's ``patternSize``."""
        return self.columns, self.rows

    @property
    def num_corners(self) -> int:
        return self.columns * self.rows

    def object_points(self) -> np.ndarray:
        """Inner corners in the board frame, ``(N, 3)`` float64, row by row (OpenCV's order), Z = 0."""
        r, c = np.divmod(np.arange(self.num_corners), self.columns)
        return np.stack([c * self.square_size, r * self.square_size, np.zeros(self.num_corners)], axis=1)

    def labels(self, X: np.ndarray, Y: np.ndarray, *, margin: float | None = None) -> np.ndarray:
        """What is printed at board coordinates ``(X, Y)`` (metres, any shape): BLACK, WHITE or BACKGROUND.

        The squares are surrounded by a white paper margin of ``margin`` metres (default one square);
        outside the paper is BACKGROUND. Square ``(a, b)``, spanning ``[a s, (a + 1) s] x [b s, (b + 1) s]``,
        is black when ``a + b`` is even.
        """
        s = self.square_size
        margin = s if margin is None else margin
        X = np.asarray(X)
        Y = np.asarray(Y)
        a = np.floor(X / s)
        b = np.floor(Y / s)
        in_squares = (a >= -1) & (a <= self.columns - 1) & (b >= -1) & (b <= self.rows - 1)
        black = in_squares & ((a + b) % 2 == 0)
        in_paper = (X >= -s - margin) & (X <= self.columns * s + margin) & (Y >= -s - margin) \
            & (Y <= self.rows * s + margin)
        out = np.where(in_paper, WHITE, BACKGROUND).astype(np.int8)
        out[black] = BLACK
        return out

    def mesh(self) -> Mesh:
        """The printed squares as a triangle mesh in the board frame (Z = 0), black and white vertex colours.

        Four vertices per square (so each square has one flat colour), two triangles each.
        """
        s = self.square_size
        a, b = np.meshgrid(np.arange(-1, self.columns), np.arange(-1, self.rows), indexing="xy")
        a, b = a.ravel(), b.ravel()
        x0, y0 = a * s, b * s
        corners = np.stack([np.stack([x0, y0], 1), np.stack([x0 + s, y0], 1), np.stack([x0 + s, y0 + s], 1),
                            np.stack([x0, y0 + s], 1)], axis=1)  # (S, 4, 2)
        vertices = np.concatenate([corners.reshape(-1, 2), np.zeros((corners.size // 2, 1))], axis=1)
        base = 4 * np.arange(len(a))[:, None]
        faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=0)
        shade = np.where((a + b) % 2 == 0, 0.05, 0.95)
        colors = np.repeat(np.repeat(shade[:, None], 3, axis=1), 4, axis=0)
        return Mesh(vertices, faces, colors)


# --- the synthetic generator ----------------------------------------------------------------------------
def synthetic(*, columns: Annotated[int, Range(3, 20)] = 9, rows: Annotated[int, Range(3, 20)] = 6,
              square_size: Annotated[float, Range(0.001, 1.0)] = 0.025,
              num_views: Annotated[int, Range(3, 60)] = 15,
              width: Annotated[int, Range(160, 4096)] = 640, height: Annotated[int, Range(120, 4096)] = 480,
              fx: Annotated[float, Range(50.0, 20000.0)] = 350.0,
              fy: Annotated[float, Range(50.0, 20000.0)] = 347.0,
              cx: Annotated[float, Range(0.0, 4096.0)] = 318.0, cy: Annotated[float, Range(0.0, 4096.0)] = 242.0,
              k1: Annotated[float, Range(-1.0, 1.0)] = -0.25, k2: Annotated[float, Range(-1.0, 1.0)] = 0.08,
              p1: Annotated[float, Range(-0.05, 0.05)] = 0.0008, p2: Annotated[float, Range(-0.05, 0.05)] = -0.0006,
              k3: Annotated[float, Range(-1.0, 1.0)] = 0.0,
              pose_spread_deg: Annotated[float, Range(5.0, 65.0)] = 40.0,
              noise_px: Annotated[float, Range(0.0, 5.0)] = 0.2,
              blur_px: Annotated[float, Range(0.0, 3.0)] = 0.7,
              image_noise: Annotated[float, Range(0.0, 0.2)] = 0.01,
              color: bool = False, seed: int = 0) -> Loaded:
    """A checkerboard seen by a camera with known intrinsics, distortion and poses (exact ground truth).

    Each view tilts the board by 50 to 100 % of ``pose_spread_deg`` about an axis in its plane
    (the axes spread evenly around the circle, as Zhang's method needs non-parallel views),
    turns it in its plane by up to half that, and places it so that the whole paper lies inside
    the image. Each image is rendered by following every pixel's ray: undistort its coordinate
    (Newton's method), intersect the ray with the board plane, and average the printed pattern
    exactly over the pixel's footprint on the board (anti-aliasing by an analytic box filter,
    which supersampling approximates: 4 x 4 samples quantize an edge aligned with the pixel grid
    to a quarter pixel); then blur by the lens's point spread function (a Gaussian of
    ``blur_px``), which real photos have and which ``cv2.cornerSubPix`` needs to be unbiased.

    Corner noise: each corner ``i`` gets an image displacement ``d_i ~ N(0, noise_px^2)`` per
    axis. The displacements are turned into board coordinates (through the local Jacobian of the
    projection) and interpolated bilinearly over the corner grid into a smooth field ``D``; a
    pixel shows the board at ``b(x) - D(b(x))``, so corner ``i`` appears at ``p_i + d_i`` while the
    truth keeps the exact projection ``p_i``. Then Gaussian pixel noise of ``image_noise``.
    Rendering 15 views of 640 x 480 takes about a second.

    Args:
        columns: inner corners per row of the board.
        rows: inner corners per column of the board.
        square_size: side of a square in metres.
        num_views: number of photos.
        width: image width in pixels.
        height: image height in pixels.
        fx: focal length along x in pixels.
        fy: focal length along y in pixels.
        cx: principal point x in pixels.
        cy: principal point y in pixels.
        k1: radial distortion (r^2).
        k2: radial distortion (r^4).
        p1: tangential distortion.
        p2: tangential distortion.
        k3: radial distortion (r^6).
        pose_spread_deg: largest tilt of the board away from facing the camera, in degrees.
        noise_px: standard deviation of each corner's displacement per axis, in pixels.
        blur_px: standard deviation of the lens blur in pixels (0: none).
        image_noise: standard deviation of the pixel noise (intensities in [0, 1]).
        color: render RGB images (tinted paper and background) instead of grayscale.
        seed: random seed of the poses and the noise.

    Truth: ``K`` (3, 3), ``dist`` (5,), ``rotations`` (V, 3, 3), ``translations`` (V, 3) (board to
    camera), ``corners`` (Points2D of the exact projections, ``view`` and ``ids`` set).
    """
    import cv2

    check_dataset_pixels(views=num_views, width=width, height=height)
    board = Checkerboard(columns, rows, square_size)
    if not (0 <= cx < width and 0 <= cy < height):
        raise InvalidValue("cx", f"the principal point ({cx}, {cy}) must lie inside the {width}x{height} image")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    dist = as_distortion([k1, k2, p1, p2, k3])
    rng = np.random.default_rng(seed)
    pixel_grid = _PixelRays(K, dist, width, height)
    R, t = _sample_poses(board, K, dist, width, height, num_views, pose_spread_deg, rng)
    points = board.object_points()
    exact = project_points(points[None], K, dist, R, t)  # (V, N, 2)
    displacement = rng.normal(0.0, noise_px, exact.shape) if noise_px > 0 else np.zeros(exact.shape)
    images = []
    for v in range(num_views):
        board_shift = _board_displacements(board, K, dist, R[v], t[v], displacement[v]).astype(np.float32)
        pixels = _render(board, pixel_grid, K, dist, R[v], t[v], board_shift, color=color)
        if blur_px > 0:
            pixels = cv2.GaussianBlur(pixels, (0, 0), blur_px, borderType=cv2.BORDER_REPLICATE)
        if image_noise > 0:
            pixels = pixels + rng.normal(0.0, image_noise, pixels.shape)
        images.append(Image(np.clip(pixels, 0.0, 1.0).astype(np.float32), name=f"view {v:02d}"))
    n = board.num_corners
    truth_corners = Points2D(exact.reshape(-1, 2), view=np.repeat(np.arange(num_views), n),
                             ids=np.tile(np.arange(n), num_views), image="images")
    truth = {"K": K, "dist": dist, "rotations": R, "translations": t, "corners": truth_corners}
    description = (f"Synthetic: a {columns}x{rows} board ({square_size * 1000:g} mm squares) in {num_views} "
                   f"views of {width}x{height} px, fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g}, "
                   f"k1={k1:g} k2={k2:g} p1={p1:g} p2={p2:g} k3={k3:g}, corner noise {noise_px:g} px")
    return Loaded({"images": ImageSet(tuple(images)), "board": board}, truth, description)


class _PixelRays:
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
        # float32 for the per-view tracing: board coordinates to ~1e-7 of their size, far below a pixel
        as32 = lambda value: np.ascontiguousarray(value, dtype=np.float32)  # noqa: E731
        self.x, self.y = as32(x), as32(y)
        self.x_u, self.x_v = as32(i00 * k00), as32(i00 * k01 + i01 * k11)
        self.y_u, self.y_v = as32(i01 * k00), as32(i01 * k01 + i11 * k11)
        self.width = width
        self.height = height


def _paper_outline(board: Checkerboard, per_edge: int = 25) -> np.ndarray:
    """Points along the edge of the paper (the squares plus a one-square white margin), ``(4 per_edge, 3)``."""
    s = board.square_size
    x0, x1, y0, y1 = -2 * s, (board.columns + 1) * s, -2 * s, (board.rows + 1) * s
    edge = np.linspace(0.0, 1.0, per_edge)
    xs, ys = x0 + (x1 - x0) * edge, y0 + (y1 - y0) * edge
    outline = np.concatenate([np.stack([xs, np.full_like(xs, y0)], 1), np.stack([xs, np.full_like(xs, y1)], 1),
                              np.stack([np.full_like(ys, x0), ys], 1), np.stack([np.full_like(ys, x1), ys], 1)])
    return np.concatenate([outline, np.zeros((len(outline), 1))], axis=1)


#: Range of the paper's width as a fraction of the image width, and how far (as a fraction of the image
#: size) the board's centre may move from the principal point: large boards all over the image
#: constrain the principal point and the distortion best.
_PAPER_FRACTION = (0.7, 0.95)
_JITTER = 0.3


def _sample_poses(board: Checkerboard, K: np.ndarray, dist: np.ndarray, width: int, height: int,
                  num_views: int, spread_deg: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Board-to-camera poses ``R`` (V, 3, 3), ``t`` (V, 3) with the whole paper inside the image."""
    s = board.square_size
    centre = np.array([(board.columns - 1) * s / 2, (board.rows - 1) * s / 2, 0.0])
    outline = _paper_outline(board)
    paper_width = (board.columns + 3) * s
    spread = np.radians(spread_deg)
    phase = rng.uniform(0, 2 * np.pi)
    rotations, translations = [], []
    border = 3.0
    for v in range(num_views):
        for _attempt in range(500):
            phi = phase + 2 * np.pi * (v + rng.uniform(-0.3, 0.3)) / num_views
            tilt = spread * rng.uniform(0.5, 1.0)
            roll = spread * rng.uniform(-0.5, 0.5)
            R = rotvec_to_matrix(tilt * np.array([np.cos(phi), np.sin(phi), 0.0])) \
                @ rotvec_to_matrix(np.array([0.0, 0.0, roll]))
            fraction = rng.uniform(*_PAPER_FRACTION) * 0.99**_attempt  # smaller boards after failed tries
            depth = K[0, 0] * paper_width / (fraction * width)
            target = K[:2, 2] + rng.uniform(-1, 1, 2) * _JITTER * np.array([width, height])
            ray = np.linalg.solve(K, np.append(target, 1.0))
            t = depth * ray - R @ centre
            camera_points = outline @ R.T + t
            if np.min(camera_points[:, 2]) <= 1e-3 * depth:
                continue
            pixels = project_points(outline, K, dist, R, t)
            if np.all(np.isfinite(pixels)) and np.all(pixels >= border) and np.all(pixels[:, 0] <= width - 1 - border) \
                    and np.all(pixels[:, 1] <= height - 1 - border):
                rotations.append(R)
                translations.append(t)
                break
        else:
            raise InvalidValue("pose_spread_deg", "could not place the board inside the image in 500 tries; "
                                                  "lower pose_spread_deg or the focal lengths")
    return np.array(rotations), np.array(translations)


def _board_displacements(board: Checkerboard, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
                         displacement: np.ndarray) -> np.ndarray:
    """Image displacements ``(N, 2)`` of the corners as board-plane displacements ``(rows, columns, 2)``.

    ``delta_b_i = J_i^-1 d_i`` with ``J_i`` = d(pixel)/d(board X, Y) at corner ``i`` (central
    differences, all corners at once).
    """
    points = board.object_points()
    h = 1e-6 * board.square_size
    offsets = np.array([[h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0]])
    shifted = project_points(points[None] + offsets[:, None], K, dist, R, t)  # (4, N, 2)
    J = np.stack([(shifted[0] - shifted[1]) / (2 * h), (shifted[2] - shifted[3]) / (2 * h)], axis=-1)  # (N, 2, 2)
    board_shift = np.linalg.solve(J, displacement[..., None])[..., 0]
    return board_shift.reshape(board.rows, board.columns, 2)


def _interpolate_grid(board: Checkerboard, values: np.ndarray, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
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


_PALETTE_GRAY = np.array([0.06, 0.94, 0.4])  # black, white, background
_PALETTE_RGB = np.array([[0.07, 0.06, 0.06], [0.95, 0.93, 0.88], [0.30, 0.42, 0.55]])


def _box_fractions(board: Checkerboard, X: np.ndarray, Y: np.ndarray, reach_x: np.ndarray,
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

    def mean(integral, centre: np.ndarray, reach: np.ndarray) -> np.ndarray:
        return (integral(centre + reach) - integral(centre - reach)) / (2.0 * reach)

    rect_x = mean(lambda u: np.clip(u, lo_x, hi_x), X, reach_x)
    rect_y = mean(lambda u: np.clip(u, lo_y, hi_y), Y, reach_y)
    alt_x = mean(lambda u: triangle(np.clip(u, lo_x, hi_x)), X, reach_x)
    alt_y = mean(lambda u: triangle(np.clip(u, lo_y, hi_y)), Y, reach_y)
    paper = mean(lambda u: np.clip(u, lo_x - s, hi_x + s), X, reach_x) \
        * mean(lambda u: np.clip(u, lo_y - s, hi_y + s), Y, reach_y)
    return 0.5 * (rect_x * rect_y + alt_x * alt_y), paper


def _render(board: Checkerboard, rays: _PixelRays, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
            board_shift: np.ndarray, *, color: bool) -> np.ndarray:
    """One view: ``(H, W)`` or ``(H, W, 3)`` float64 in [0, 1], anti-aliased (see :func:`synthetic`).

    Each pixel's ray meets the board at ``(X, Y)`` (the inverse of the board-to-normalized
    homography ``[r1 r2 t]``); the pixel's footprint on the board, a small parallelogram given
    by the derivative of that map, is replaced by its bounding box, over which the pattern is
    averaged exactly (:func:`_box_fractions`). This is the box filter that supersampling
    approximates (4 x 4 samples would quantize an edge parallel to the pixel grid to a quarter
    pixel), and a symmetric blur, so it moves no edge and no corner. Only the bounding box of the
    paper (plus 3 px) is traced; the rest is background.
    """
    palette = _PALETTE_RGB if color else _PALETTE_GRAY
    out = np.empty((rays.height, rays.width) + palette.shape[1:])
    out[...] = palette[BACKGROUND]
    outline = project_points(_paper_outline(board), K, dist, R, t)
    c0, r0 = np.maximum(np.floor(outline.min(axis=0) - 3).astype(int), 0)
    c1, r1 = np.minimum(np.ceil(outline.max(axis=0) + 4).astype(int), (rays.width, rays.height))
    if c1 <= c0 or r1 <= r0:
        return out
    T = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t])).astype(np.float32)  # normalized -> board, homogeneous
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
        shift = _interpolate_grid(board, board_shift, X, Y)
        X = X - shift[..., 0]
        Y = Y - shift[..., 1]
    black, paper = _box_fractions(board, X, Y, reach_x, reach_y)
    black = np.where(front, black, 0.0)
    paper = np.where(front, paper, 0.0)
    weights = (black, paper - black, 1.0 - paper)
    if color:
        out[crop] = sum(w[..., None] * palette[k] for k, w in enumerate(weights))
    else:
        out[crop] = sum(w * palette[k] for k, w in enumerate(weights))
    return out


# --- a user's folder of photos ------------------------------------------------------------------------
def folder(*, path: str, columns: Annotated[int, Range(2, 100)] = 9, rows: Annotated[int, Range(2, 100)] = 6,
           square_size: Annotated[float, Range(1e-6, 100.0)] = 0.025, pattern: str = "*") -> Loaded:
    """A folder of checkerboard photos (any format OpenCV reads), sorted by file name; no truth.

    Args:
        path: the folder that holds the photos.
        columns: inner corners per row of the board.
        rows: inner corners per column of the board.
        square_size: side of a square in metres.
        pattern: shell pattern of the file names to read (e.g. ``left*.jpg``); files that are not
            images are skipped.
    """
    from lab.data.files import IMAGE_SUFFIXES, list_images, read_images

    board = Checkerboard(columns, rows, square_size)
    files = list_images(path, pattern)
    if not files:
        raise InvalidValue("path", f"folder {path!r} holds no images matching {pattern!r} "
                                   f"(readable endings: {', '.join(IMAGE_SUFFIXES)})")
    images = read_images(files)
    description = (f"{len(images)} photos from {path} ({columns}x{rows} inner corners, "
                   f"{square_size * 1000:g} mm squares)")
    return Loaded({"images": ImageSet(tuple(images)), "board": board}, {}, description)


__all__ = ["Checkerboard", "synthetic", "folder", "BLACK", "WHITE", "BACKGROUND"]
