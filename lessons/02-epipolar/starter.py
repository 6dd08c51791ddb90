"""Lesson 02, epipolar geometry: fill in the three functions, then run

    vision-lab grade 02-epipolar starter.py

You may import numpy, scipy and cv2 (not the lab's own implementation). Keep the signatures.

Conventions: pixels are (u, v) = (column, row); camera 1 is the world frame and camera 2 sees
X_2 = R X_1 + t; x2^T F x1 = 0; E = [t]_x R = K2^T F K1.
"""

import numpy as np


def estimate_fundamental_8point(x1, x2, *, normalize=True):
    """The fundamental matrix of all the matches by the (normalized) 8-point algorithm, rank 2.

    Args:
        x1: (M, 2) float64 pixels in image 1, M >= 8.
        x2: (M, 2) float64 pixels in image 2; row i of x1 and row i of x2 are one match.
        normalize: first move each point set so that its centroid is at the origin and its mean
            distance from it is sqrt(2) (T1 for x1, T2 for x2), and undo it at the end:
            F = T2^T F_n T1. With normalize=False use the pixels as they are.

    Returns:
        (3, 3) float64 F with x2^T F x1 = 0: the right singular vector of A for its smallest
        singular value (one row [u2 u1, u2 v1, u2, v2 u1, v2 v1, v2, u1, v1, 1] per match, f row by
        row), made rank 2 (smallest singular value set to 0) before undoing the normalization, and
        scaled to unit Frobenius norm (either sign).
    """
    raise NotImplementedError


def decompose_essential(E):
    """The four relative poses [R | t] an essential matrix admits.

    Args:
        E: (3, 3) float64 with singular values (1, 1, 0).

    Returns:
        (4, 3, 4) float64: [R1 | t], [R2 | t], [R1 | -t], [R2 | -t], in any order (they are checked as a
        set), with U, S, Vt = np.linalg.svd(E) (U negated if det(U) < 0, Vt negated if det(Vt) < 0: each R
        must be a rotation, det +1), W = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], R1 = U W Vt, R2 = U W^T Vt
        and t = U[:, 2] (unit length).
    """
    raise NotImplementedError


def recover_pose(candidates, x1, x2, K1, K2, inliers=None, *, candidate="cheirality"):
    """Of the four candidates, the pose that puts the most inliers in front of both cameras.

    Args:
        candidates: (4, 3, 4) float64, the output of decompose_essential.
        x1, x2: (M, 2) float64 matched pixels in image 1 and image 2.
        K1, K2: (3, 3) float64 camera matrices of image 1 and image 2.
        inliers: (M,) bool, the matches to use (None: all of them).
        candidate: "cheirality" (the test: what is graded), or one of "R1 t", "R2 t", "R1 -t",
            "R2 -t": then return that candidate (index 0, 1, 2, 3) without any test.

    Returns:
        (3, 4) float64: the chosen candidate [R | t] itself (one of the four, unchanged). For each
        candidate, triangulate every inlier (normalized coordinates K^-1 x, P1 = [I | 0],
        P2 = [R | t], linear DLT) and count the points with positive depth in both cameras: Z of X
        in camera 1 and Z of R X + t in camera 2 (both positive: one camera alone is not enough).
        Keep the candidate with the highest count (the first one on a tie).
    """
    raise NotImplementedError
