"""Similarity alignment of point sets and of cameras (Umeyama 1991).

A reconstruction from photos alone is known only up to a similarity ``X' = s Q X + d`` (scale, rotation,
translation): SfM's frame is the first camera's, its unit the first baseline's. To compare it with the
truth, or to bring true cameras into its frame (evaluation tools such as nerfstudio's and COLMAP's
``model_aligner`` do it this way), the similarity of least squared error between matching camera centres is
estimated (:func:`umeyama`, the same as scikit-image's ``SimilarityTransform.estimate``) and applied to
points (:func:`apply_similarity`) or to world-to-camera poses (:func:`similarity_of_cameras`).

Conventions: cameras are world to camera, ``X_c = R X_w + t`` (DESIGN.md section 3), centres
``C = -R^T t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lab.core.errors import InvalidValue


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``target ~ s Q source + d`` of least squared error (Umeyama 1991):
    ``(s, Q (3, 3), d (3,))``.

    Centre both sets, ``Sigma = T_c^T S_c / n``, ``U D V^T = svd(Sigma)``,
    ``Q = U diag(1, 1, det(U V^T)) V^T``,
    ``s = trace(diag(D) diag(1, 1, +-1)) / var(S)``, ``d = mean(T) - s Q mean(S)``. Corresponds to
    scikit-image's ``SimilarityTransform.estimate`` (which calls ``_umeyama``).

    Reference: S. Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", TPAMI 13(4), 1991.
    """
    S = np.asarray(source, dtype=np.float64)
    T = np.asarray(target, dtype=np.float64)
    ms, mt = S.mean(axis=0), T.mean(axis=0)
    Sc, Tc = S - ms, T - mt
    sigma = Tc.T @ Sc / len(S)
    U, D, Vt = np.linalg.svd(sigma)
    sign = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        sign[2] = -1.0
    Q = U @ np.diag(sign) @ Vt
    variance = np.mean(np.sum(Sc**2, axis=1))
    s = float(np.sum(D * sign) / variance) if variance > 0 else 1.0
    return s, Q, mt - s * Q @ ms


@dataclass(frozen=True)
class Similarity:
    """``X' = scale Q X + offset``: ``scale`` > 0, ``Q`` ``(3, 3)`` a rotation, ``offset`` ``(3,)``."""

    scale: float
    Q: np.ndarray
    offset: np.ndarray

    def inverse(self) -> Similarity:
        """``X = (1 / scale) Q^T X' - (1 / scale) Q^T offset``."""
        return Similarity(1.0 / self.scale, self.Q.T.copy(), -(self.Q.T @ self.offset) / self.scale)


def camera_centers(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``C = -R^T t`` of world-to-camera poses ``R`` ``(V, 3, 3)``, ``t`` ``(V, 3)``: ``(V, 3)``."""
    return -np.einsum("nji,nj->ni", np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64))


def align_cameras(R_source: np.ndarray, t_source: np.ndarray, R_target: np.ndarray, t_target: np.ndarray,
                  *, min_spread: float = 1e-3) -> Similarity:
    """The similarity taking the source cameras' world onto the target's: :func:`umeyama` of the camera
    centres (``C_target ~ s Q C_source + d``).

    The centres must span a plane or a volume (``V >= 3``, second singular value of the centred target
    centres above ``min_spread`` times the first): on a line the rotation about it is not determined and
    :class:`InvalidValue` (field ``cameras``) says so. Shapes: ``R_*`` ``(V, 3, 3)``, ``t_*`` ``(V, 3)``.
    """
    C_source, C_target = camera_centers(R_source, t_source), camera_centers(R_target, t_target)
    if C_source.shape != C_target.shape or C_source.ndim != 2 or C_source.shape[1] != 3:
        raise InvalidValue("cameras", f"expected the same number of source and target cameras, got "
                                      f"{C_source.shape} and {C_target.shape} centres")
    if not (np.all(np.isfinite(C_source)) and np.all(np.isfinite(C_target))):
        raise InvalidValue("cameras", "camera poses contain NaN or infinite entries")
    if len(C_target) < 3 or _flat(C_target, min_spread):
        raise InvalidValue("cameras", f"{len(C_target)} camera centres do not span a plane: a similarity "
                                      "needs at least 3 centres off one line")
    s, Q, d = umeyama(C_source, C_target)
    return Similarity(s, Q, d)


def _flat(centers: np.ndarray, min_spread: float) -> bool:
    """Whether ``centers`` ``(V >= 3, 3)`` lie on a line: the second singular value of the centred set at
    most ``min_spread`` times the first."""
    spread = np.linalg.svd(centers - centers.mean(axis=0), compute_uv=False)
    return bool(spread[1] <= min_spread * max(float(spread[0]), 1e-300))


def apply_similarity(similarity: Similarity, points: np.ndarray) -> np.ndarray:
    """``s Q X + d`` of points ``(..., 3)``."""
    X = np.asarray(points, dtype=np.float64)
    return similarity.scale * X @ similarity.Q.T + similarity.offset


def similarity_of_cameras(similarity: Similarity, R: np.ndarray,
                          t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera poses moved by ``X' = s Q X + d``: ``R' = R Q^T``, ``t' = s t - R' d``, so that
    ``R' X' + t' = s (R X + t)`` (the camera frame scaled with the world, its image unchanged).
    Shapes: ``R`` ``(V, 3, 3)``, ``t`` ``(V, 3)``."""
    R_new = np.asarray(R, dtype=np.float64) @ similarity.Q.T
    t_new = similarity.scale * np.asarray(t, dtype=np.float64) - np.einsum("nij,j->ni", R_new,
                                                                           similarity.offset)
    return R_new, t_new


__all__ = ["Similarity", "align_cameras", "apply_similarity", "camera_centers", "similarity_of_cameras",
           "umeyama"]
