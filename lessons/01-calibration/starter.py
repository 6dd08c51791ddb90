"""Lesson 01, camera calibration: fill in both functions, then run

    vision-lab grade 01-calibration starter.py

You may import numpy, scipy and cv2 (not the lab's own implementation). Keep the signatures.
"""

import numpy as np


def estimate_homographies(corners, board_points, *, normalize=True):
    """One homography per view, board plane (X, Y, 1) -> pixels, by the (normalized) DLT.

    Args:
        corners: lab.core.Points2D. ``corners.xy`` (N, 2) float64 pixels, ``corners.view`` (N,) int
            the image each corner lies in, ``corners.ids`` (N,) int the board corner it is. A view may
            hold only some of the board's corners, in any order, and views may come interleaved.
        board_points: (B, 3) float64 board corners in metres (Z = 0); corner k of a view is at
            ``board_points[corners.ids[k], :2]``.
        normalize: move both point sets so their centroid is at the origin and their mean distance
            from it is sqrt(2) before the DLT, and undo it afterwards (Hartley & Zisserman, alg. 4.2).

    Returns:
        (M, 3, 3) float64: one H per view, in the order of ``np.unique(corners.view)``, each scaled
        so that ``H[2, 2] == 1``.
    """
    raise NotImplementedError


def estimate_intrinsics(homographies, *, zero_skew=False):
    """Closed-form intrinsics K from the homographies (Zhang 2000, section 3.1 and appendix B).

    Args:
        homographies: (M, 3, 3) float64, board -> pixels, M >= 3 (M >= 2 with zero_skew).
        zero_skew: impose B12 = 0 (so the skew gamma = 0) instead of estimating it.

    Returns:
        (3, 3) float64 ``[[alpha, gamma, u0], [0, beta, v0], [0, 0, 1]]``. Scale each H to unit norm
        before stacking the rows v12 and v11 - v22; estimate gamma unless zero_skew.
    """
    raise NotImplementedError
