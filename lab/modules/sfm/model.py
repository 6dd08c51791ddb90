"""The reconstruction while a step grows it (:class:`GrowingModel`), and what is measured of it.

A step reads a :class:`~lab.data.reconstruction.SparseModel`, thaws it into a :class:`GrowingModel`
(:meth:`GrowingModel.of`: copies of the arrays it changes in place), works on it, and writes the
result as a new SparseModel (:func:`freeze`). Observations are implicit, as in the SparseModel:
keypoint ``k`` observes point ``p`` when its track (``track_of[k]``) is the point's
(``point_tracks[p]``), its view is registered and it is still ``observed``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from lab.core import Points2D
from lab.data.reconstruction import SparseModel, observations_of
from lab.modules.sfm._checks import keypoint_views


def poses_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``[R | t]`` ``(..., 3, 4)`` of rotations ``(..., 3, 3)`` and translations ``(..., 3)``."""
    return np.concatenate([R, t[..., None]], axis=-1)


def ray_angles_deg(centers: np.ndarray, X: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Largest angle (deg) between two rays from the observing camera centres to each point.

    ``centers`` ``(V, 3)``, ``X`` ``(n, 3)``, ``mask`` ``(V, n)``; a point seen once gets 0.
    """
    rays = X[None] - centers[:, None]  # (V, n, 3)
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-300)
    cos = np.einsum("ank,bnk->nab", rays, rays)
    both = mask.T[:, :, None] & mask.T[:, None, :]
    cos = np.where(both, cos, 1.0)
    return np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0)))


def sample_colors(image: Any, xy: np.ndarray) -> np.ndarray:
    """Colours ``(N, 3)`` in [0, 1] of the pixels nearest to ``xy``."""
    cols = np.clip(np.round(xy[:, 0]).astype(int), 0, image.width - 1)
    rows = np.clip(np.round(xy[:, 1]).astype(int), 0, image.height - 1)
    values = image.pixels[rows, cols].astype(np.float64)
    return values if values.ndim == 2 else np.repeat(values[:, None], 3, axis=1)


def error_colors(errors: np.ndarray, scale: float) -> np.ndarray:
    """Green (0 px) to red (``scale`` px and more), ``(N, 3)``."""
    s = np.clip(np.asarray(errors, dtype=np.float64) / max(scale, 1e-9), 0.0, 1.0)[:, None]
    return (1 - s) * np.array([0.1, 0.8, 0.2]) + s * np.array([0.9, 0.1, 0.1])


@dataclass
class GrowingModel:
    """The reconstruction while it grows (mutable inside a step; the state gets copies).

    ``poses`` ``(V, 3, 4)``, ``registered`` ``(V,)`` bool, ``points`` ``(P, 3)``, ``point_tracks``
    ``(P,)`` int (the track of each point), ``observed`` ``(N,)`` bool (keypoints still used).
    """

    poses: np.ndarray
    registered: np.ndarray
    points: np.ndarray
    point_tracks: np.ndarray
    observed: np.ndarray

    @classmethod
    def of(cls, model: SparseModel) -> GrowingModel:
        """A growing copy of ``model`` (its tracks ``model.track_of`` stay apart: copy them to change
        them)."""
        return cls(model.poses.copy(), model.registered.copy(), model.points.copy(),
                   model.point_tracks.copy(), model.observed.copy())

    def point_of_track(self, num_tracks: int) -> np.ndarray:
        """The point of every track ``(T,)`` (-1: none)."""
        size = max(num_tracks, int(self.point_tracks.max()) + 1 if len(self.point_tracks) else 0)
        out = np.full(size, -1, dtype=np.int64)
        out[self.point_tracks] = np.arange(len(self.point_tracks))
        return out

    def observations(self, keypoints: Points2D,
                     track_of: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(keypoint index, view, point index)`` of every usable observation of a reconstructed point
        (:func:`lab.data.reconstruction.observations_of`)."""
        return observations_of(keypoint_views(keypoints), track_of, self.point_tracks, self.registered,
                               self.observed)

    def copy(self) -> GrowingModel:
        return GrowingModel(self.poses.copy(), self.registered.copy(), self.points.copy(),
                            self.point_tracks.copy(), self.observed.copy())


def project(model: GrowingModel, K: np.ndarray, views: np.ndarray, points: np.ndarray,
            X: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(n, 2)`` and depths ``(n,)`` of ``points`` (or of positions ``X``) in ``views``."""
    X = model.points[points] if X is None else X
    Xc = np.einsum("nij,nj->ni", model.poses[views, :, :3], X) + model.poses[views, :, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.einsum("nij,nj->ni", K[views], Xc / Xc[:, 2:3])[:, :2]
    return uv, Xc[:, 2]


def observation_errors(model: GrowingModel, K: np.ndarray, keypoints: Points2D, kp: np.ndarray,
                       views: np.ndarray, points: np.ndarray, X: np.ndarray | None = None) -> np.ndarray:
    """Reprojection error (px) of each observation ``(keypoint, view, point)`` (the point at ``X`` when
    given); ``inf`` behind the camera."""
    uv, depth = project(model, K, views, points, X)
    errors = np.linalg.norm(uv - keypoints.xy[kp], axis=1)
    return np.where((depth > 0) & np.isfinite(errors), errors, np.inf)


def point_colors(keypoints: Points2D, model: GrowingModel, track_of: np.ndarray) -> np.ndarray:
    """Mean colour over each point's observations ``(P, 3)``."""
    kp, _, point = model.observations(keypoints, track_of)
    colors = keypoints.colors if keypoints.colors is not None else np.full((len(keypoints), 3), 0.7)
    sums = np.zeros((len(model.points), 3))
    np.add.at(sums, point, colors[kp])
    counts = np.bincount(point, minlength=len(model.points))[:, None]
    return np.where(counts > 0, sums / np.maximum(counts, 1), 0.7)


def point_errors(model: GrowingModel, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray) -> np.ndarray:
    """Mean reprojection error (px) of each point's observations ``(P,)``; observations behind their camera
    do not count, a point without any gets 0."""
    kp, views, point = model.observations(keypoints, track_of)
    errors = observation_errors(model, K, keypoints, kp, views, point)
    finite = np.isfinite(errors)
    counts = np.bincount(point[finite], minlength=len(model.points))
    sums = np.bincount(point[finite], weights=errors[finite], minlength=len(model.points))
    return np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)


def freeze(model: GrowingModel, track_of: np.ndarray, K: np.ndarray, keypoints: Points2D,
           names: tuple[str, ...], sizes: np.ndarray) -> SparseModel:
    """The growing ``model`` with its tracks ``track_of`` as a :class:`SparseModel` (copies), with each
    point's colour (the mean over its observations) and reprojection error (:func:`point_errors`)."""
    colors = np.round(255 * np.clip(point_colors(keypoints, model, track_of), 0, 1)).astype(np.uint8)
    return SparseModel(K=K, poses=model.poses, registered=model.registered, names=names, sizes=sizes,
                       keypoints=keypoints, track_of=track_of, observed=model.observed, points=model.points,
                       point_tracks=model.point_tracks, colors=colors,
                       errors=point_errors(model, K, keypoints, track_of))


def refreeze(model: GrowingModel, track_of: np.ndarray, like: SparseModel,
             K: np.ndarray | None = None) -> SparseModel:
    """:func:`freeze` with the images (names, sizes), keypoints and, unless given, ``K`` of ``like``."""
    return freeze(model, track_of, like.K if K is None else K, like.keypoints, like.names, like.sizes)
