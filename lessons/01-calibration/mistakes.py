"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each is built from the
lab's own functions, so it is exact by construction.
"""

import numpy as np

from lab.core import Points2D
from lab.geometry.homogeneous import hartley_normalization
from lab.modules.calibration import estimate_homographies, estimate_intrinsics
from lab.modules.calibration.homography import ViewStack, dlt_homographies, stack_views
from lab.modules.calibration.intrinsics import absolute_conic, intrinsics_from_conic, zhang_v


def homographies_reshaped_by_columns(corners, board_points, *, normalize=True):
    """The DLT's solution vector reshaped column by column: the *normalized* H_n is transposed.

    Without normalization that is the transpose of H (the ``transposed`` detector sees it); with
    it, ``T_img^-1 H_n^T T_board`` is no simple transform of the right H, hence this function.
    """
    homographies = estimate_homographies(corners, board_points, normalize=normalize)
    wrong = []
    for view, H in zip(np.unique(corners.view), homographies):
        seen = corners.view == view
        T_image = hartley_normalization(corners.xy[seen])[0] if normalize else np.eye(3)
        T_board = hartley_normalization(board_points[corners.ids[seen], :2])[0] if normalize else np.eye(3)
        H_normalized = T_image @ H @ np.linalg.inv(T_board)
        W = np.linalg.inv(T_image) @ H_normalized.T @ T_board
        wrong.append(W / W[2, 2])
    return np.array(wrong)


def homographies_ignoring_ids(corners, board_points, *, normalize=True):
    """Corner k of a view paired with board corner k (``board_points[:n]``), ``corners.ids`` never read.

    Right only when every view lists all its corners in board order; on partial, shuffled views the
    pairs are wrong.
    """
    view = np.asarray(corners.view)
    assumed = np.empty(len(view), dtype=np.int64)
    for v in np.unique(view):
        mine = np.flatnonzero(view == v)
        if len(mine) > len(board_points):
            raise ValueError("more corners in a view than on the board")
        assumed[mine] = np.arange(len(mine))
    paired = Points2D(corners.xy, view=view, ids=assumed, image=corners.image)
    return estimate_homographies(paired, board_points, normalize=normalize)


def homographies_by_cv2_findhomography(corners, board_points, *, normalize=True):
    """``cv2.findHomography(board_xy, pixels, 0)`` per view: the DLT refined by Levenberg-Marquardt on the
    reprojection error, not the DLT's own answer (``normalize`` plays no part)."""
    import cv2

    found = []
    for v in np.unique(corners.view):
        seen = corners.view == v
        H, _ = cv2.findHomography(board_points[corners.ids[seen], :2].astype(np.float64),
                                  corners.xy[seen].astype(np.float64), 0)
        if H is None:
            raise ValueError("cv2.findHomography found no homography")
        found.append(H / H[2, 2])
    return np.array(found)


def homographies_pixels_to_board(corners, board_points, *, normalize=True):
    """The DLT with the roles of the two point sets swapped: H maps pixels to the board."""
    stack = stack_views(corners, np.asarray(board_points, dtype=np.float64))
    swapped = ViewStack(stack.board_xy, stack.image_xy, stack.mask, stack.views)
    return dlt_homographies(swapped, normalize=normalize)


def normalization_undone_backwards(corners, board_points, *, normalize=True):
    """``H = T_pixels H_n T_board^-1`` where ``T_pixels^-1 H_n T_board`` undoes the normalization."""
    homographies = estimate_homographies(corners, board_points, normalize=normalize)
    if not normalize:
        return homographies
    wrong = []
    for view, H in zip(np.unique(corners.view), homographies):
        seen = corners.view == view
        T_image = hartley_normalization(corners.xy[seen])[0]
        T_board = hartley_normalization(board_points[corners.ids[seen], :2])[0]
        H_normalized = T_image @ H @ np.linalg.inv(T_board)
        W = T_image @ H_normalized @ np.linalg.inv(T_board)
        wrong.append(W / W[2, 2])
    return np.array(wrong)


def intrinsics_without_unit_norm(homographies, *, zero_skew=False):
    """Zhang's closed form on the homographies as given (H[2, 2] = 1), not scaled to unit norm first:
    the views weigh unequally, which changes b on noisy data."""
    H = np.asarray(homographies, dtype=np.float64)
    V = np.concatenate([zhang_v(H, 0, 1), zhang_v(H, 0, 0) - zhang_v(H, 1, 1)], axis=0)
    if zero_skew:
        reduced = np.delete(V, 1, axis=1)
        b = np.insert(np.linalg.svd(reduced)[2][-1], 1, 0.0)
        return intrinsics_from_conic(-b if b[0] < 0 else b, zero_skew=True)
    return intrinsics_from_conic(absolute_conic(V), zero_skew=False)


def zero_skew_by_dropping_gamma(homographies, *, zero_skew=False):
    """With zero_skew, the full solution with gamma set to 0 afterwards (``u0 = -B13 alpha^2 / lambda``)
    instead of solving with B12 = 0."""
    if not zero_skew:
        return estimate_intrinsics(homographies)
    H = np.asarray(homographies, dtype=np.float64)
    H = H / np.linalg.norm(H, axis=(1, 2), keepdims=True)
    V = np.concatenate([zhang_v(H, 0, 1), zhang_v(H, 0, 0) - zhang_v(H, 1, 1)], axis=0)
    return intrinsics_from_conic(absolute_conic(V), zero_skew=True)
