"""The interchange form of a sparse reconstruction: cameras, keypoints, 3D points and their tracks.

What COLMAP's text model, ``transforms.json`` and the SfM module's result have in common, in the
lab's conventions (DESIGN.md section 3): OpenCV camera frame, world to camera ``X_c = R X_w + t``,
pixel (0, 0) the centre of the top-left pixel. Readers and writers of other formats convert at
their edge (:mod:`lab.data.colmap`, :mod:`lab.data.transforms_json`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lab.core.errors import InvalidValue
from lab.core.values import Cameras, PointCloud


def _array(value: object, name: str, shape: tuple[int | None, ...], dtype: type) -> np.ndarray:
    try:
        array = np.asarray(value)
        if dtype is np.uint8:
            if array.size and (not np.issubdtype(array.dtype, np.integer) and not np.all(array == np.round(array))
                               or array.min() < 0 or array.max() > 255):
                raise InvalidValue(name, "colours must be integers in [0, 255]")
        elif dtype is np.int64 and array.size and not np.issubdtype(array.dtype, np.integer) \
                and not (np.all(np.isfinite(array)) and np.all(array == np.round(array))):
            raise InvalidValue(name, "expected integers")
        array = array.astype(dtype)
    except (TypeError, ValueError) as exc:
        raise InvalidValue(name, f"cannot be read as a {np.dtype(dtype).name} array: {exc}") from None
    if array.ndim != len(shape) or any(want is not None and got != want for got, want in zip(array.shape, shape)):
        pretty = ", ".join("*" if s is None else str(s) for s in shape)
        raise InvalidValue(name, f"expected shape ({pretty}), got {array.shape}")
    if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return array


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """A sparse model: ``N`` registered images and ``M`` 3D points with their tracks.

    Fields:
        K: ``(N, 3, 3)`` intrinsics per image (``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``).
        sizes: ``(N, 2)`` int, ``(width, height)`` of each image in pixels.
        R: ``(N, 3, 3)`` world-to-camera rotations; t: ``(N, 3)``: ``X_c = R X_w + t`` (OpenCV).
        names: ``N`` image file names (relative, no whitespace for COLMAP).
        keypoints: ``N`` arrays ``(K_i, 2)`` float64, the 2D features of each image (pixels).
        xyz: ``(M, 3)`` point positions; colors: ``(M, 3)`` uint8 RGB; errors: ``(M,)`` mean
            reprojection error of each point in pixels.
        tracks: ``M`` arrays ``(L_j, 2)`` int64 of ``(image index, keypoint index)``, the
            observations of point ``j`` (0-based indices into ``names`` and ``keypoints[i]``).

    Arrays are converted to the dtypes above; shapes and indices are checked (InvalidValue names
    the field). Value equality is :meth:`equals` (exact, array by array).
    """

    K: np.ndarray
    sizes: np.ndarray
    R: np.ndarray
    t: np.ndarray
    names: tuple[str, ...]
    keypoints: tuple[np.ndarray, ...]
    xyz: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    tracks: tuple[np.ndarray, ...]

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64) if not isinstance(self.K, np.ndarray) else self.K
        n = len(K) if np.ndim(K) == 3 else -1
        if n < 0:
            raise InvalidValue("K", f"expected (N, 3, 3) intrinsics, got shape {np.shape(K)}")
        set_ = object.__setattr__
        set_(self, "K", _array(self.K, "K", (n, 3, 3), np.float64))
        if np.any(self.K[:, 2] != (0.0, 0.0, 1.0)) or np.any(self.K[:, 1, 0] != 0.0) \
                or np.any(self.K[:, 0, 0] <= 0) or np.any(self.K[:, 1, 1] <= 0):
            raise InvalidValue("K", "every K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with positive focal lengths")
        set_(self, "sizes", _array(self.sizes, "sizes", (n, 2), np.int64))
        if np.any(self.sizes < 1):
            raise InvalidValue("sizes", "image sizes (width, height) must be positive")
        set_(self, "R", _array(self.R, "R", (n, 3, 3), np.float64))
        set_(self, "t", _array(self.t, "t", (n, 3), np.float64))
        if isinstance(self.names, str):
            raise InvalidValue("names", "expected a sequence of image names, got one string")
        names = tuple(self.names)
        if len(names) != n or not all(isinstance(name, str) and name for name in names):
            raise InvalidValue("names", f"expected {n} non-empty image names, got {len(names)}")
        if len(set(names)) != n:
            raise InvalidValue("names", "image names must be unique")
        set_(self, "names", names)
        keypoints = tuple(self.keypoints)
        if len(keypoints) != n:
            raise InvalidValue("keypoints", f"expected {n} keypoint arrays (one per image), got {len(keypoints)}")
        set_(self, "keypoints", tuple(_array(k, f"keypoints[{i}]", (None, 2), np.float64)
                                      for i, k in enumerate(keypoints)))
        xyz = _array(self.xyz, "xyz", (None, 3), np.float64)
        m = len(xyz)
        set_(self, "xyz", xyz)
        set_(self, "colors", _array(self.colors, "colors", (m, 3), np.uint8))
        set_(self, "errors", _array(self.errors, "errors", (m,), np.float64))
        tracks = tuple(self.tracks)
        if len(tracks) != m:
            raise InvalidValue("tracks", f"expected {m} tracks (one per point), got {len(tracks)}")
        counts = np.array([len(k) for k in self.keypoints])
        checked = []
        for j, track in enumerate(tracks):
            track = _array(np.asarray(track).reshape(-1, 2) if np.size(track) == 0 else track, f"tracks[{j}]",
                           (None, 2), np.int64)
            if len(track) and (track[:, 0].min() < 0 or track[:, 0].max() >= n):
                raise InvalidValue(f"tracks[{j}]", f"image indices must lie in [0, {n})")
            if len(track) and (np.any(track[:, 1] < 0) or np.any(track[:, 1] >= counts[track[:, 0]])):
                raise InvalidValue(f"tracks[{j}]", "keypoint index out of range of its image's keypoints")
            checked.append(track)
        set_(self, "tracks", tuple(checked))

    def __len__(self) -> int:
        return len(self.K)

    @property
    def centers(self) -> np.ndarray:
        """Camera centres in the world, ``(N, 3)``: ``C = -R^T t``."""
        return -np.einsum("nji,nj->ni", self.R, self.t)

    @property
    def mean_track_length(self) -> float:
        """Observations per point, averaged over the points (0 without points)."""
        return float(np.mean([len(track) for track in self.tracks])) if self.tracks else 0.0

    def cameras(self, *, image: str = "", colors: np.ndarray | None = None) -> Cameras:
        """The cameras as the viewer's typed value (:class:`lab.core.values.Cameras`).

        ``Cameras`` has one image size: the first image's (frustum aspect only). ``image`` names
        an image set in state whose view ``i`` camera ``i`` carries; ``colors`` ``(N, 3)`` in [0, 1].
        """
        return Cameras(K=self.K, R=self.R, t=self.t, width=int(self.sizes[0, 0]), height=int(self.sizes[0, 1]),
                       image=image, colors=colors)

    def point_cloud(self) -> PointCloud:
        """The points with their colours as the viewer's typed value (colours scaled to [0, 1])."""
        return PointCloud(self.xyz, self.colors / 255.0)

    def equals(self, other: object) -> bool:
        """Exact equality, field by field and array by array (dtype, shape and every bit of value)."""
        if not isinstance(other, Reconstruction):
            return False
        if self.names != other.names or len(self.keypoints) != len(other.keypoints) \
                or len(self.tracks) != len(other.tracks):
            return False
        pairs = [(self.K, other.K), (self.sizes, other.sizes), (self.R, other.R), (self.t, other.t),
                 (self.xyz, other.xyz), (self.colors, other.colors), (self.errors, other.errors)]
        pairs += list(zip(self.keypoints, other.keypoints)) + list(zip(self.tracks, other.tracks))
        return all(a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b) for a, b in pairs)


__all__ = ["Reconstruction"]
