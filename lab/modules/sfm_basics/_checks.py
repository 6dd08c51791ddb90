"""Checks of the lesson pipeline's inputs: each returns the value as the math uses it or raises
:class:`~lab.core.InvalidValue` naming the input."""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.core import InvalidValue, Points2D


def check_observations(observations: Any) -> Points2D:
    if not isinstance(observations, Points2D):
        raise InvalidValue("observations", f"expected Points2D, got {type(observations).__name__}")
    if observations.view is None or observations.ids is None:
        raise InvalidValue("observations", "needs view (the camera) and ids (the 3D point) of every pixel")
    if len(observations) == 0:
        raise InvalidValue("observations", "there are no observations")
    if observations.view.min() < 0 or observations.ids.min() < 0:
        raise InvalidValue("observations", "view and ids must be non-negative indices")
    return observations


def check_points(points: Any, name: str, count: int | None = None) -> np.ndarray:
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or (count is not None and len(X) != count):
        want = "(N, 3)" if count is None else f"({count}, 3)"
        raise InvalidValue(name, f"expected {want} points, got shape {X.shape}")
    if not np.all(np.isfinite(X)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return X


def check_poses(poses: Any, name: str, count: int | None = None) -> np.ndarray:
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (3, 4) or (count is not None and len(P) != count):
        want = "(V, 3, 4)" if count is None else f"({count}, 3, 4)"
        raise InvalidValue(name, f"expected {want} [R | t] matrices, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return P


def views_and_ids(observations: Points2D) -> tuple[np.ndarray, np.ndarray]:
    """The camera ``view`` and the point ``ids`` of every observation (checked observations have both)."""
    assert observations.view is not None and observations.ids is not None
    return observations.view, observations.ids


def view_count(observations: Points2D) -> int:
    views = np.unique(views_and_ids(observations)[0])
    if not np.array_equal(views, np.arange(len(views))):
        raise InvalidValue("observations", f"cameras must be numbered 0 .. V-1 without gaps, "
                                           f"got views {views.tolist()}")
    return len(views)


def point_count(observations: Points2D, points: np.ndarray | None = None) -> int:
    count = int(views_and_ids(observations)[1].max()) + 1
    if points is not None:
        if len(points) < count:
            raise InvalidValue("observations",
                               f"ids go up to {count - 1} but there are {len(points)} 3D points")
        count = len(points)
    return count



def stacked(observations: Points2D, V: int, N: int) -> tuple[np.ndarray, np.ndarray]:
    """Observations as ``(V, N, 2)`` pixels and a ``(V, N)`` mask (a camera sees a point at most once)."""
    view, ids = views_and_ids(observations)
    x = np.zeros((V, N, 2))
    mask = np.zeros((V, N), dtype=bool)
    if np.any(view >= V):
        raise InvalidValue("observations", f"a view index is {int(view.max())} but there are {V} poses")
    flat = view * N + ids
    if len(np.unique(flat)) != len(flat):
        raise InvalidValue("observations", "a camera observes the same point twice")
    x[view, ids] = observations.xy
    mask[view, ids] = True
    seen = mask.sum(axis=0)
    if np.any(seen < 2):
        raise InvalidValue("observations",
                           f"point {int(np.flatnonzero(seen < 2)[0])} is seen by fewer than two "
                           "cameras: it cannot be triangulated")
    return x, mask


def check_indices(camera_indices: Any, point_indices: Any, num_cameras: Any,
                  num_points: Any) -> tuple[np.ndarray, ...]:
    cameras = np.asarray(camera_indices)
    points = np.asarray(point_indices)
    if cameras.ndim != 1 or points.shape != cameras.shape or len(cameras) == 0:
        raise InvalidValue("camera_indices",
                           f"camera and point indices must be two non-empty (M,) arrays of the same "
                           f"length, got {cameras.shape} and {points.shape}")
    if not (np.issubdtype(cameras.dtype, np.integer) and np.issubdtype(points.dtype, np.integer)):
        raise InvalidValue("camera_indices", "indices must be integers")
    for name, value in (("num_cameras", num_cameras), ("num_points", num_points)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise InvalidValue(name, f"must be a positive integer, got {value!r}")
    return cameras.astype(np.int64), points.astype(np.int64)

