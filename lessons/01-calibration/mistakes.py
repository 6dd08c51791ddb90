"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each is built from the
lab's own functions, so it is exact by construction.
"""

import numpy as np

from lab.geometry.homogeneous import hartley_normalization
from lab.modules.calibration import estimate_homographies


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
