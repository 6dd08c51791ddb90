"""Finding the board's inner corners in a photo and refining them to sub-pixel accuracy.

The coarse detection is OpenCV's (``cv2.findChessboardCorners``); :func:`orient` puts corner 0 at
the black square's end so that ids match the board in every view; :func:`refine_corners` is
Förstner's gradient-orthogonality iteration, what ``cv2.cornerSubPix`` computes, written out and
vectorized over all corners of all photos.

Reference: W. Förstner and E. Gülch, "A fast operator for detection and precise location of
distinct points, corners and centres of circular features", ISPRS 1987; OpenCV's ``cornerSubPix``
(imgproc/src/cornersubpix.cpp).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lab.core import ImageSet, InvalidControl, InvalidValue
from lab.modules.calibration.board import Checkerboard


@dataclass
class FoundBoards:
    """The photos in which the whole board was found: their grayscale images, corners and indices."""

    grays: list[np.ndarray] = field(default_factory=list)
    xy: list[np.ndarray] = field(default_factory=list)
    views: list[int] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def find_boards(images: ImageSet, board: Checkerboard) -> FoundBoards:
    """``cv2.findChessboardCorners`` (adaptive threshold, normalized image) on every photo's 8-bit gray,
    the corners oriented by :func:`orient`; a warning names each photo without the whole board."""
    import cv2

    found = FoundBoards()
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    for index, (name, image) in enumerate(zip(images.names, images.images, strict=True)):
        gray = image.gray()
        gray8 = np.clip(gray * 255.0 + 0.5, 0, 255).astype(np.uint8)
        ok, xy = cv2.findChessboardCorners(gray8, board.pattern_size, flags=flags)
        if not ok or xy is None or len(xy) != board.num_corners:
            found.warnings.append(f"{name}: no {board.columns}x{board.rows} board found")
            continue
        found.grays.append(gray)
        found.xy.append(orient(gray, xy.reshape(-1, 2).astype(np.float64), board))
        found.views.append(index)
    return found


def orient(gray: np.ndarray, xy: np.ndarray, board: Checkerboard) -> np.ndarray:
    """Put corner 0 where the square between corners 0, 1, columns, columns + 1 is black.

    ``cv2.findChessboardCorners`` may start from either end of the board. When ``columns + rows``
    is odd the board has no 180-degree symmetry, and the colour of that square tells the ends
    apart (reverse the order if it is lighter than its neighbour along the row).
    """
    if (board.columns + board.rows) % 2 == 0:
        return xy
    grid = xy.reshape(board.rows, board.columns, 2)
    first = grid[:2, :2].reshape(-1, 2).mean(axis=0)
    neighbour = grid[:2, 1:3].reshape(-1, 2).mean(axis=0)
    h, w = gray.shape
    offsets = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1]), -1).reshape(1, 9, 2)
    probe = np.stack([first, neighbour])[:, None, :] + offsets
    cols = np.clip(np.round(probe[..., 0]).astype(int), 0, w - 1)
    rows = np.clip(np.round(probe[..., 1]).astype(int), 0, h - 1)
    shade = gray[rows, cols].mean(axis=1)
    return xy[::-1].copy() if shade[0] > shade[1] else xy


def refine_corners(gray: np.ndarray, xy: np.ndarray, view: np.ndarray | None = None, *, window: int = 5,
                   max_iterations: int = 30, epsilon: float = 1e-3) -> np.ndarray:
    """Sub-pixel corner positions by Förstner's gradient-orthogonality iteration, all corners at once.

    At the true corner ``q`` every image gradient ``g_p`` near it is orthogonal to ``p - q`` (on an
    edge ``g_p`` is normal to the edge through ``q``; in a flat region ``g_p = 0``). Minimizing
    ``sum_p w_p (g_p^T (p - q))^2`` over the window gives the 2x2 linear system
    ``(sum w g g^T) q = sum w g g^T p``; iterate with the window re-centred on the new ``q``.
    This is exactly ``cv2.cornerSubPix(gray, xy, (window, window), (-1, -1), criteria)``: the
    window is ``2 window + 1`` pixels wide, sampled bilinearly around ``q`` (``cv2.getRectSubPix``,
    border replicated), gradients are central differences, weights ``exp(-(dx^2 + dy^2) / window^2)``;
    a corner stops when it moves less than ``epsilon`` px or leaves the image, and one that ends
    up more than ``window`` px from its start keeps its start.

    Args:
        gray: ``(H, W)`` or a stack ``(V, H, W)`` of grayscale images (float).
        xy: ``(N, 2)`` initial corners in pixels.
        view: ``(N,)`` index into the stack for each corner (None: all on image 0).
        window: half the side of the search window, in pixels.
        max_iterations: most iterations per corner.
        epsilon: stop when a corner moves less than this (pixels).

    Returns:
        ``(N, 2)`` refined corners.

    Reference: W. Förstner and E. Gülch, "A fast operator for detection and precise location of
    distinct points, corners and centres of circular features", ISPRS 1987; OpenCV's
    ``cornerSubPix`` (imgproc/src/cornersubpix.cpp).
    """
    stack = np.asarray(gray, dtype=np.float32)
    if stack.ndim == 2:
        stack = stack[None]
    if stack.ndim != 3:
        raise InvalidValue("gray", f"expected (H, W) or (V, H, W), got shape {stack.shape}")
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    count = len(stack)
    view = np.zeros(len(xy), dtype=np.intp) if view is None else np.asarray(view, dtype=np.intp)
    if len(view) != len(xy) or (len(view) and (view.min() < 0 or view.max() >= count)):
        raise InvalidValue("view", "needs one image index per corner")
    if int(window) < 1:
        raise InvalidControl("window", f"must be at least 1, got {window}")
    half = int(window)
    window_weights = _window_moments(half)
    start = xy.copy()
    q = xy.copy()
    active = np.arange(len(q))
    eps2 = float(epsilon) ** 2
    for _ in range(int(max_iterations)):
        if len(active) == 0:
            break
        centre = q[active]
        sums = _gradient_moments(stack, view[active], centre, half, window_weights)
        step, solvable = _solve_corner_step(sums)
        moved = np.where(solvable[:, None], centre + step, centre)
        q[active] = moved
        height, width = stack.shape[1:]
        inside = (moved[:, 0] >= 0) & (moved[:, 0] < width) & (moved[:, 1] >= 0) & (moved[:, 1] < height)
        active = active[solvable & inside & (np.sum(step * step, axis=1) > eps2)]
    far = np.any(np.abs(q - start) > half, axis=1)
    q[far] = start[far]
    return q


def _window_moments(half: int) -> np.ndarray:
    """``(S^2, 3)`` columns ``w``, ``w px``, ``w py`` over the ``S = 2 half + 1`` window, Gaussian ``w``."""
    size = 2 * half + 1
    grid = ((np.arange(size) - half) / half) ** 2
    weights = np.exp(-grid[:, None] - grid[None, :]).astype(np.float32)  # (S, S)
    px = (np.arange(size, dtype=np.float32) - half)[None, :]  # x offset of window column j
    py = (np.arange(size, dtype=np.float32) - half)[:, None]  # y offset of window row i
    return np.stack([weights, weights * px, weights * py], axis=-1).reshape(-1, 3)


def _gradient_moments(stack: np.ndarray, view: np.ndarray, centre: np.ndarray, half: int,
                      window_weights: np.ndarray) -> np.ndarray:
    """``(n, 3, 3)`` window sums of ``g g^T`` (gxx, gxy, gyy) times ``w``, ``w px``, ``w py`` at each centre.

    One gather of the ``(S + 3)^2`` pixels around each centre (border replicated), then a bilinear
    patch in which all pixels share the centre's fractional weights (``cv2.getRectSubPix``) and
    central-difference gradients inside it.
    """
    _, height, width = stack.shape
    reach = np.arange(-half - 1, half + 3)  # pixels under the bilinear (S + 2)^2 patch and its 1 px border
    flat = stack.reshape(-1)
    base = np.floor(centre).astype(np.intp)
    frac = (centre - base).astype(np.float32)
    cols = np.clip(base[:, 0, None] + reach, 0, width - 1)
    rows = np.clip(base[:, 1, None] + reach, 0, height - 1)
    pixels = flat[(view * (height * width))[:, None, None] + rows[:, :, None] * width + cols[:, None, :]]
    fx = frac[:, 0, None, None]
    fy = frac[:, 1, None, None]
    top = pixels[:, :-1, :-1] + fx * (pixels[:, :-1, 1:] - pixels[:, :-1, :-1])
    bottom = pixels[:, 1:, :-1] + fx * (pixels[:, 1:, 1:] - pixels[:, 1:, :-1])
    patch = top + fy * (bottom - top)  # (n, S + 2, S + 2)
    gx = patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2]
    gy = patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1]
    products = np.stack([gx * gx, gx * gy, gy * gy], axis=1).reshape(len(centre), 3, -1)
    return (products @ window_weights).astype(np.float64)


def _solve_corner_step(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The move ``(n, 2)`` that solves each corner's 2x2 system, and whether it was solvable ``(n,)``."""
    a, b, c = sums[:, 0, 0], sums[:, 1, 0], sums[:, 2, 0]
    bb1 = sums[:, 0, 1] + sums[:, 1, 2]  # sum w (gxx px + gxy py)
    bb2 = sums[:, 1, 1] + sums[:, 2, 2]  # sum w (gxy px + gyy py)
    det = a * c - b * b
    solvable = np.abs(det) > np.finfo(np.float64).eps ** 2
    safe = np.where(solvable, det, 1.0)
    step = np.stack([(c * bb1 - b * bb2) / safe, (a * bb2 - b * bb1) / safe], axis=1)
    return step, solvable


__all__ = ["FoundBoards", "find_boards", "orient", "refine_corners"]
