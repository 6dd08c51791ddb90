"""One homography per view, board plane ``(X, Y, 1)`` -> pixels, by the (normalized) DLT.

Each correspondence ``(X, Y) -> (u, v)`` gives two rows of ``A h = 0``::

    [X, Y, 1, 0, 0, 0, -u X, -u Y, -u]
    [0, 0, 0, X, Y, 1, -v X, -v Y, -v]

and ``h`` is the right singular vector of ``A`` with the smallest singular value. All views are
solved at once by one batched SVD: :func:`stack_views` lays the corners out as ``(M views, S
slots)``, padding views with fewer points with zero rows, which change nothing.

Reference: Hartley & Zisserman, Multiple View Geometry (2nd ed.), section 4.1 (DLT) and 4.4
(normalization, algorithm 4.2); Z. Zhang (2000), appendix A.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lab.core import InvalidValue, Points2D
from lab.geometry.homogeneous import hartley_normalization
from lab.modules.calibration.observations import views_of


@dataclass(frozen=True)
class ViewStack:
    """Corners laid out by view: ``image_xy`` and ``board_xy`` ``(M, S, 2)``, ``mask`` ``(M, S)`` marks
    the real points (the rest is zero padding), ``views`` ``(M,)`` the sorted image indices."""

    image_xy: np.ndarray
    board_xy: np.ndarray
    mask: np.ndarray
    views: np.ndarray


def stack_views(corners: Points2D, board_points: np.ndarray) -> ViewStack:
    """The checked corners and the board points they observe, one row of slots per view (at least 4 each)."""
    views, position = views_of(corners)
    counts = np.bincount(position, minlength=len(views))
    if np.any(counts < 4):
        bad = views[counts < 4]
        raise InvalidValue("corners", "a homography needs at least 4 points per view; "
                                      f"view(s) {bad.tolist()} have fewer")
    order = np.argsort(position, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(order)) - starts[position[order]]
    size = int(counts.max())
    image_xy = np.zeros((len(views), size, 2))
    board_xy = np.zeros((len(views), size, 2))
    mask = np.zeros((len(views), size), dtype=bool)
    image_xy[position[order], slot] = corners.xy[order]
    board_xy[position[order], slot] = board_points[np.asarray(corners.ids)[order], :2]
    mask[position[order], slot] = True
    return ViewStack(image_xy, board_xy, mask, views)


def dlt_homographies(stack: ViewStack, *, normalize: bool) -> np.ndarray:
    """``(M, 3, 3)`` homographies with ``H[2, 2] = 1`` by the DLT, batched over the views.

    With ``normalize`` both point sets are first moved to their centroid and scaled to mean distance
    sqrt(2) (``T_img``, ``T_board``), and ``H = T_img^-1 H_n T_board`` (H&Z algorithm 4.2).
    """
    image_xy, board_xy, mask = stack.image_xy, stack.board_xy, stack.mask
    if normalize:
        T_image, image_xy = hartley_normalization(image_xy, mask)
        T_board, board_xy = hartley_normalization(board_xy, mask)
        image_xy[~mask] = 0.0
        board_xy[~mask] = 0.0
    X, Y = board_xy[..., 0], board_xy[..., 1]
    u, v = image_xy[..., 0], image_xy[..., 1]
    one, zero = mask.astype(np.float64), np.zeros_like(X)
    rows_u = np.stack([X, Y, one, zero, zero, zero, -u * X, -u * Y, -u], axis=-1)
    rows_v = np.stack([zero, zero, zero, X, Y, one, -v * X, -v * Y, -v], axis=-1)
    A = np.concatenate([rows_u, rows_v], axis=1)  # (M, 2 size, 9)
    _, singular, Vt = np.linalg.svd(A, full_matrices=False)
    degenerate = singular[:, -2] <= 1e-10 * singular[:, 0]
    if np.any(degenerate):
        raise InvalidValue("corners", f"view(s) {stack.views[degenerate].tolist()}: the points do not "
                                      "determine a homography (collinear or repeated points?)")
    H = Vt[:, -1].reshape(-1, 3, 3)
    if normalize:
        H = np.linalg.solve(T_image, H @ T_board)
    scale = H[:, 2, 2]
    if np.any(np.abs(scale) < 1e-12 * np.abs(H).max(axis=(1, 2))):
        raise InvalidValue("corners", "a homography maps the board origin to infinity; "
                                      "the input is degenerate")
    return H / scale[:, None, None]


__all__ = ["ViewStack", "dlt_homographies", "stack_views"]
