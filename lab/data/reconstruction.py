"""The sparse reconstruction: cameras, keypoints, 3D points, and which keypoints observe which point.

:class:`SparseModel` is the lab's one sparse reconstruction. The SfM module's steps pass it from
stage to stage (the two-view model, the incremental one, the filtered one, the bundle-adjusted one),
the viewer reads it, and the writers and readers of other formats take and give it
(:mod:`lab.data.colmap`, :mod:`lab.data.transforms_json`, :func:`lab.data.exports.write_reconstruction`).

Conventions (DESIGN.md section 3): OpenCV camera frame, world to camera ``X_c = R X_w + t``, pixel
(0, 0) the centre of the top-left pixel; other formats convert at their edge.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from numpy.typing import ArrayLike

from lab.core.errors import InvalidValue
from lab.core.values import Cameras, PointCloud, Points2D


def _array(value: object, name: str, shape: tuple[int | None, ...], dtype: type) -> np.ndarray:
    try:
        array = np.asarray(value)
        if dtype is np.uint8:
            integral = np.issubdtype(array.dtype, np.integer) or bool(np.all(array == np.round(array)))
            if array.size and (not integral or array.min() < 0 or array.max() > 255):
                raise InvalidValue(name, "colours must be integers in [0, 255]")
        elif dtype is np.int64 and array.size and not np.issubdtype(array.dtype, np.integer) \
                and not (np.all(np.isfinite(array)) and np.all(array == np.round(array))):
            raise InvalidValue(name, "expected integers")
        array = array.astype(dtype)
    except (TypeError, ValueError) as exc:
        raise InvalidValue(name, f"cannot be read as a {np.dtype(dtype).name} array: {exc}") from None
    if array.ndim != len(shape) or any(want is not None and got != want
                                       for got, want in zip(array.shape, shape, strict=True)):
        pretty = ", ".join("*" if s is None else str(s) for s in shape)
        raise InvalidValue(name, f"expected shape ({pretty}), got {array.shape}")
    if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return array


def observations_of(view: np.ndarray, track_of: np.ndarray, point_tracks: np.ndarray, registered: np.ndarray,
                    observed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(keypoint, view, point)`` index arrays of every observation, in keypoint order.

    Keypoint ``k`` (in view ``view[k]``) observes point ``p`` when its track ``track_of[k]`` is the
    point's (``point_tracks[p]``), its view is ``registered`` and it is still ``observed``.
    """
    num_tracks = int(track_of.max()) + 1 if len(track_of) and track_of.max() >= 0 else 0
    size = max(num_tracks, int(point_tracks.max()) + 1 if len(point_tracks) else 0)
    of_track = np.full(size, -1, dtype=np.int64)
    of_track[point_tracks] = np.arange(len(point_tracks))
    point = np.where(track_of >= 0, of_track[np.maximum(track_of, 0)], -1) if num_tracks else \
        np.full(len(track_of), -1)
    use = (point >= 0) & registered[view] & observed
    kp = np.flatnonzero(use)
    return kp, view[kp], point[kp]


@dataclass(frozen=True, eq=False)
class SparseModel:
    """A sparse reconstruction of ``V`` views with ``N`` keypoints and ``P`` points.

    Fields:
        K: ``(V, 3, 3)`` intrinsics per view (``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``).
        poses: ``(V, 3, 4)`` ``[R | t]``, world to camera (``X_c = R X_w + t``); meaningful where
            ``registered``.
        registered: ``(V,)`` bool, the views whose pose is known.
        names: ``V`` image names; sizes: ``(V, 2)`` int ``(width, height)`` in pixels.
        keypoints: the ``N`` keypoints of all views (:class:`~lab.core.values.Points2D`, ``view`` per
            keypoint, optional ``colors`` in [0, 1]).
        track_of: ``(N,)`` int, the track of each keypoint (-1: none); a track is the keypoints
            that see one scene point, at most one per view.
        observed: ``(N,)`` bool, the keypoints used as observations.
        points: ``(P, 3)`` positions; point_tracks: ``(P,)`` int, the track of each point (distinct).
        colors: ``(P, 3)`` uint8 RGB; errors: ``(P,)`` mean reprojection error of each point's
            observations in pixels.

    Keypoint ``k`` observes point ``p`` when ``track_of[k] == point_tracks[p]``, its view is
    registered and ``observed[k]`` (:meth:`observations`). The SfM steps keep their tracks here
    (keypoints of a track with no point, keypoints they stopped using); a model read from a file
    has one track per point (:meth:`from_tracks`) and :meth:`compact` turns any model into that
    form. Arrays are converted to the dtypes above; shapes and indices are checked
    (:class:`InvalidValue` names the field). Value equality is :meth:`equals`.
    """

    K: np.ndarray
    poses: np.ndarray
    registered: np.ndarray
    names: tuple[str, ...]
    sizes: np.ndarray
    keypoints: Points2D
    track_of: np.ndarray
    observed: np.ndarray
    points: np.ndarray
    point_tracks: np.ndarray
    colors: np.ndarray
    errors: np.ndarray

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        K = _array(self.K, "K", (None, 3, 3), np.float64)
        v = len(K)
        if v < 1:
            raise InvalidValue("K", "a model has at least one view")
        if not np.all(np.isclose(K[:, 2], (0.0, 0.0, 1.0))) or np.any(K[:, 1, 0] != 0.0) \
                or np.any(K[:, 0, 0] <= 0) or np.any(K[:, 1, 1] <= 0):
            raise InvalidValue("K", "every K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with positive "
                                    "focal lengths")
        set_(self, "K", K)
        set_(self, "poses", _array(self.poses, "poses", (v, 3, 4), np.float64))
        set_(self, "registered", _array(self.registered, "registered", (v,), np.bool_))
        if isinstance(self.names, str):
            raise InvalidValue("names", "expected a sequence of image names, got one string")
        names = tuple(self.names)
        if len(names) != v or not all(isinstance(name, str) and name for name in names):
            raise InvalidValue("names", f"expected {v} non-empty image names, got {len(names)}")
        set_(self, "names", names)
        set_(self, "sizes", _array(self.sizes, "sizes", (v, 2), np.int64))
        if np.any(self.sizes < 1):
            raise InvalidValue("sizes", "image sizes (width, height) must be positive")
        view = self.keypoints.view if isinstance(self.keypoints, Points2D) else None
        if view is None:
            raise InvalidValue("keypoints", "expected Points2D with a view per keypoint")
        if len(view) and (view.min() < 0 or view.max() >= v):
            raise InvalidValue("keypoints", f"keypoint views must lie in [0, {v})")
        n = len(self.keypoints)
        set_(self, "track_of", _array(self.track_of, "track_of", (n,), np.int64))
        if len(self.track_of) and self.track_of.min() < -1:
            raise InvalidValue("track_of", "track ids are non-negative (-1: no track)")
        set_(self, "observed", _array(self.observed, "observed", (n,), np.bool_))
        points = _array(self.points, "points", (None, 3), np.float64)
        p = len(points)
        set_(self, "points", points)
        set_(self, "point_tracks", _array(self.point_tracks, "point_tracks", (p,), np.int64))
        if p and (self.point_tracks.min() < 0 or len(np.unique(self.point_tracks)) != p):
            raise InvalidValue("point_tracks", "every point has its own track (distinct, non-negative ids)")
        set_(self, "colors", _array(self.colors, "colors", (p, 3), np.uint8))
        set_(self, "errors", _array(self.errors, "errors", (p,), np.float64))

    # --- what the model holds -----------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.K)

    @property
    def view(self) -> np.ndarray:
        """The view of every keypoint ``(N,)``."""
        assert self.keypoints.view is not None  # checked on construction
        return self.keypoints.view

    @property
    def R(self) -> np.ndarray:
        """World-to-camera rotations ``(V, 3, 3)``."""
        return self.poses[:, :, :3]

    @property
    def t(self) -> np.ndarray:
        """World-to-camera translations ``(V, 3)``."""
        return self.poses[:, :, 3]

    @property
    def centers(self) -> np.ndarray:
        """Camera centres in the world, ``(V, 3)``: ``C = -R^T t``."""
        return -np.einsum("nji,nj->ni", self.R, self.t)

    def observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(keypoint, view, point)`` of every observation, in keypoint order (:func:`observations_of`)."""
        return observations_of(self.view, self.track_of, self.point_tracks, self.registered, self.observed)

    def point_of_keypoint(self) -> np.ndarray:
        """The point each keypoint observes ``(N,)`` (-1: none)."""
        kp, _, point = self.observations()
        out = np.full(len(self.keypoints), -1, dtype=np.int64)
        out[kp] = point
        return out

    @property
    def mean_track_length(self) -> float:
        """Observations per point, averaged over the points (0 without points)."""
        if not len(self.points):
            return 0.0
        _, _, point = self.observations()
        return float(np.mean(np.bincount(point, minlength=len(self.points))))

    @property
    def image_keypoints(self) -> tuple[np.ndarray, ...]:
        """The pixels ``(K_i, 2)`` of each view's keypoints, in keypoint order."""
        return tuple(self.keypoints.xy[self.view == i] for i in range(len(self)))

    @property
    def tracks(self) -> tuple[np.ndarray, ...]:
        """Per point, its observations as ``(L_j, 2)`` int64 rows ``(view, keypoint index within the view)``,
        sorted by view (the form of COLMAP's ``points3D.txt``)."""
        view = self.view
        order = np.argsort(view, kind="stable")
        offsets = np.concatenate([[0], np.cumsum(np.bincount(view, minlength=len(self)))])
        local = np.empty(len(view), dtype=np.int64)
        local[order] = np.arange(len(view)) - offsets[view[order]]
        kp, views, point = self.observations()
        sort = np.lexsort((kp, views, point))
        kp, views, point = kp[sort], views[sort], point[sort]
        bounds = np.searchsorted(point, np.arange(len(self.points) + 1))
        return tuple(np.column_stack([views[s:e], local[kp[s:e]]]).astype(np.int64).reshape(-1, 2)
                     for s, e in pairwise(bounds))

    # --- as drawn -------------------------------------------------------------------------------
    def cameras(self, *, image: str = "", colors: np.ndarray | None = None) -> Cameras:
        """The registered views as the viewer's cameras (:class:`lab.core.values.Cameras`, ``views``:
        their indices).

        ``Cameras`` has one image size: the first view's (frustum aspect only). ``image`` names an
        image set in state whose views the cameras carry; ``colors`` ``(R, 3)`` in [0, 1] tints them.
        """
        views = np.flatnonzero(self.registered)
        return Cameras(K=self.K[views], R=self.R[views], t=self.t[views], width=int(self.sizes[0, 0]),
                       height=int(self.sizes[0, 1]), image=image, views=views, colors=colors)

    def point_cloud(self) -> PointCloud:
        """The points with their colours (scaled to [0, 1]) as the viewer's point cloud."""
        return PointCloud(self.points, self.colors / 255.0)

    def observation_pixels(self, *, image: str = "") -> Points2D:
        """Every observation's pixel, ``view`` its view and ``ids`` its point (drawn on the image set
        ``image``)."""
        kp, views, point = self.observations()
        return Points2D(self.keypoints.xy[kp], view=views, ids=point, image=image)

    # --- the interchange form -------------------------------------------------------------------
    @classmethod
    def from_tracks(cls, K: ArrayLike, sizes: ArrayLike, R: ArrayLike, t: ArrayLike, names: Sequence[str],
                    keypoints: Sequence[ArrayLike], points: ArrayLike, colors: ArrayLike, errors: ArrayLike,
                    tracks: Sequence[ArrayLike]) -> SparseModel:
        """A model of registered views from the form files hold: per view its keypoints ``(K_i, 2)``,
        per point its track of ``(view, keypoint index within the view)`` rows.

        Each point gets its own track (``point_tracks = 0 .. P-1``); every keypoint of a track is an
        observation. Raises :class:`InvalidValue` for a track out of range or a keypoint in two
        tracks (it observes one 3D point, as COLMAP's ``POINTS2D`` hold one ``POINT3D_ID``).
        """
        K = _array(K, "K", (None, 3, 3), np.float64)
        n = len(K)
        R = _array(R, "R", (n, 3, 3), np.float64)
        t = _array(t, "t", (n, 3), np.float64)
        keypoints = tuple(keypoints)
        if len(keypoints) != n:
            raise InvalidValue("keypoints",
                               f"expected {n} keypoint arrays (one per image), got {len(keypoints)}")
        per_view = [_array(k, f"keypoints[{i}]", (None, 2), np.float64) for i, k in enumerate(keypoints)]
        counts = np.array([len(k) for k in per_view], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        xy = np.concatenate(per_view) if per_view else np.zeros((0, 2))
        points = _array(points, "points", (None, 3), np.float64)
        tracks = tuple(tracks)
        if len(tracks) != len(points):
            raise InvalidValue("tracks", f"expected {len(points)} tracks (one per point), got {len(tracks)}")
        checked = []
        for j, track in enumerate(tracks):
            rows = _array(np.asarray(track).reshape(-1, 2) if np.size(track) == 0 else track, f"tracks[{j}]",
                          (None, 2), np.int64)
            if len(rows) and (rows[:, 0].min() < 0 or rows[:, 0].max() >= n):
                raise InvalidValue(f"tracks[{j}]", f"image indices must lie in [0, {n})")
            if len(rows) and (np.any(rows[:, 1] < 0) or np.any(rows[:, 1] >= counts[rows[:, 0]])):
                raise InvalidValue(f"tracks[{j}]", "keypoint index out of range of its image's keypoints")
            checked.append(rows)
        rows = np.concatenate(checked) if checked else np.zeros((0, 2), dtype=np.int64)
        owner = np.repeat(np.arange(len(checked)), [len(r) for r in checked])
        index = offsets[rows[:, 0]] + rows[:, 1]
        order = np.argsort(index, kind="stable")
        twice = np.flatnonzero(index[order][1:] == index[order][:-1])
        if len(twice):
            first, second = order[twice[0]], order[twice[0] + 1]
            raise InvalidValue("tracks", f"keypoint {rows[first, 1]} of image {rows[first, 0]} is in tracks "
                                         f"{owner[first]} and {owner[second]}: a keypoint observes one 3D "
                                         "point (COLMAP allows one 3D point per keypoint)")
        track_of = np.full(int(offsets[-1]), -1, dtype=np.int64)
        track_of[index] = owner
        return cls(K=K, poses=np.concatenate([R, t[:, :, None]], axis=2), registered=np.ones(n, dtype=bool),
                   names=tuple(names), sizes=_array(sizes, "sizes", (n, 2), np.int64),
                   keypoints=Points2D(xy, view=np.repeat(np.arange(n), counts), image=""),
                   track_of=track_of, observed=track_of >= 0, points=points,
                   point_tracks=np.arange(len(points)),
                   colors=_array(colors, "colors", (len(points), 3), np.uint8),
                   errors=_array(errors, "errors", (len(points),), np.float64))

    def compact(self) -> SparseModel:
        """The model as a file holds it (:meth:`from_tracks`): the registered views only, each keypoint with
        its pixel alone, one track per point holding exactly its observations."""
        reg = np.flatnonzero(self.registered)
        new_index = np.full(len(self), -1, dtype=np.int64)
        new_index[reg] = np.arange(len(reg))
        keypoints = self.image_keypoints
        return SparseModel.from_tracks(
            self.K[reg], self.sizes[reg], self.R[reg], self.t[reg], [self.names[v] for v in reg],
            [keypoints[v] for v in reg], self.points, self.colors, self.errors,
            [np.column_stack([new_index[track[:, 0]], track[:, 1]]) for track in self.tracks])

    def equals(self, other: object) -> bool:
        """Exact equality, field by field and array by array (dtype, shape and every bit of value)."""
        if not isinstance(other, SparseModel) or self.names != other.names:
            return False
        mine, theirs = self.keypoints.colors, other.keypoints.colors
        if (mine is None) != (theirs is None):
            return False
        pairs = [(self.K, other.K), (self.poses, other.poses), (self.registered, other.registered),
                 (self.sizes, other.sizes), (self.keypoints.xy, other.keypoints.xy), (self.view, other.view),
                 (self.track_of, other.track_of), (self.observed, other.observed),
                 (self.points, other.points), (self.point_tracks, other.point_tracks),
                 (self.colors, other.colors), (self.errors, other.errors)]
        if mine is not None and theirs is not None:
            pairs.append((mine, theirs))
        return all(a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b) for a, b in pairs)


__all__ = ["SparseModel", "observations_of"]
