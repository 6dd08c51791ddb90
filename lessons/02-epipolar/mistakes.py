"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each is built from the
lab's own functions, so it is exact by construction.
"""

import numpy as np

from lab.geometry.camera import pixels_to_normalized
from lab.geometry.homogeneous import hartley_normalization
from lab.geometry.triangulation import point_depths, triangulate_dlt
from lab.modules.epipolar import design_matrix, enforce_rank2, essential_candidates, recover_pose


# --- task 1: the 8-point algorithm ---------------------------------------------------------------
def _solved(pixels1, pixels2, normalized):
    """``T1``, ``T2`` and the least-squares ``F_n`` (rank 3) of the normalized (or raw) matches, as the lab's
    :func:`lab.modules.epipolar.eight_point` computes them before rank 2 and denormalization (a helper: its
    parameters are not the step's, so it is no mistake of its own)."""
    x1, x2 = np.asarray(pixels1, dtype=np.float64), np.asarray(pixels2, dtype=np.float64)
    T1, n1 = hartley_normalization(x1) if normalized else (np.eye(3), x1)
    T2, n2 = hartley_normalization(x2) if normalized else (np.eye(3), x2)
    f = np.linalg.svd(design_matrix(n1, n2))[2][-1]
    return T1, T2, f.reshape(3, 3)


def eight_point_normalization_not_undone(x1, x2, *, normalize=True):
    """``F_n`` of the normalized points returned as it is: ``T2^T F_n T1`` (undoing the normalization) left
    out."""
    _, _, F = _solved(x1, x2, normalize)
    F = enforce_rank2(F)
    return F / np.linalg.norm(F)


def eight_point_rank2_after_denormalizing(x1, x2, *, normalize=True):
    """Rank 2 enforced after undoing the normalization (on ``T2^T F_n T1``, in pixels), not on ``F_n``."""
    T1, T2, F = _solved(x1, x2, normalize)
    F = enforce_rank2(T2.T @ F @ T1)
    return F / np.linalg.norm(F)


# --- task 2: the four poses of E ---------------------------------------------------------------------
def translation_from_right_null_vector(E):
    """t taken from V's last column (E's right null vector, R^T t) instead of U's (its left null vector, t).

    The lab's four candidates with their translation replaced, V^T turned into a rotation as the
    lab does before reading it.
    """
    candidates = essential_candidates(E)
    Vt = np.linalg.svd(np.asarray(E, dtype=np.float64))[2]
    v = -Vt[2] if np.linalg.det(Vt) < 0 else Vt[2]
    candidates[:, :, 3] = np.array([1.0, 1.0, -1.0, -1.0])[:, None] * v
    return candidates


# --- task 3: the cheirality test ---------------------------------------------------------------------
def _depths(candidates, x1, x2, K1, K2):
    """Each candidate's depths ``(4, 2, M)`` of every match in camera 1 and camera 2, triangulated as the lab's
    test does (:func:`lab.modules.epipolar.cheirality_counts`: DLT on normalized coordinates)."""
    n1, n2 = pixels_to_normalized(x1, K1), pixels_to_normalized(x2, K2)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    depths = []
    for pose in np.asarray(candidates, dtype=np.float64):
        P = np.stack([P1, pose])
        X = triangulate_dlt(P, np.stack([n1, n2]))
        finite = np.all(np.isfinite(X), axis=1)
        depths.append(np.where(finite[None], point_depths(P, np.where(finite[:, None], X, 0.0)), np.nan))
    return np.array(depths)


def _chosen(candidates, x1, x2, K1, K2, inliers, candidate, counted):
    """The candidate with the most matches ``counted(depths)`` says count (the first on a tie), as the lab's
    :func:`lab.modules.epipolar.recover_pose` but for the rule; a forced ``candidate`` as the lab's."""
    if candidate != "cheirality":
        return recover_pose(candidates, x1, x2, K1, K2, inliers, candidate=candidate)
    mask = np.ones(len(x1), dtype=bool) if inliers is None else np.asarray(inliers, dtype=bool)
    depths = _depths(candidates, np.asarray(x1)[mask], np.asarray(x2)[mask], K1, K2)
    counts = [int(np.sum(counted(d))) for d in depths]
    return np.asarray(candidates, dtype=np.float64)[int(np.argmax(counts))].copy()


def cheirality_depth_sign_reversed(candidates, x1, x2, K1, K2, inliers=None, *, candidate="cheirality"):
    """The points counted when *behind* both cameras (both depths negative): it picks the mirror image
    ``(R, -t)`` of the right pose."""
    return _chosen(candidates, x1, x2, K1, K2, inliers, candidate, lambda d: (d[0] < 0) & (d[1] < 0))


def cheirality_every_match(candidates, x1, x2, K1, K2, inliers=None, *, candidate="cheirality"):
    """Every match votes, RANSAC's outliers too: the inliers mask is not read."""
    return recover_pose(candidates, x1, x2, K1, K2, None, candidate=candidate)


def cheirality_camera1_only(candidates, x1, x2, K1, K2, inliers=None, *, candidate="cheirality"):
    """A point counted when it is in front of camera 1 (Z of X > 0), whatever its depth in camera 2."""
    return _chosen(candidates, x1, x2, K1, K2, inliers, candidate, lambda d: d[0] > 0)


def cheirality_camera2_only(candidates, x1, x2, K1, K2, inliers=None, *, candidate="cheirality"):
    """A point counted when it is in front of camera 2 (Z of R X + t > 0), whatever its depth in camera 1."""
    return _chosen(candidates, x1, x2, K1, K2, inliers, candidate, lambda d: d[1] > 0)
