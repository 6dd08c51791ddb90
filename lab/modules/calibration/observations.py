"""The corners as the steps read them: checked, grouped by view, in the order of the image index.

Views are always ordered by image index: the ``m``-th homography, rotation and translation belong
to image ``views[m]`` (the ``m``-th of the sorted unique ``corners.view``). :class:`Observations`
holds the corners sorted that way, which every step after the homographies works on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from lab.core import InvalidValue, Points2D


def check_corners(corners: Any, board_points: Any) -> tuple[Points2D, np.ndarray]:
    """``corners`` (Points2D with ``ids``) and ``board_points`` ``(N >= 4, 3)`` float64, or InvalidValue."""
    if not isinstance(corners, Points2D):
        raise InvalidValue("corners", f"expected Points2D, got {type(corners).__name__}")
    if corners.ids is None:
        raise InvalidValue("corners", "needs ids (the board corner each point observes)")
    board_points = np.asarray(board_points, dtype=np.float64)
    if board_points.ndim != 2 or board_points.shape[1] != 3 or len(board_points) < 4:
        raise InvalidValue("board_points", f"expected shape (N >= 4, 3), got {board_points.shape}")
    if not np.all(np.isfinite(board_points)):
        raise InvalidValue("board_points", "contains NaN or infinite entries")
    if len(corners) and (corners.ids.min() < 0 or corners.ids.max() >= len(board_points)):
        raise InvalidValue("corners", f"ids must index board_points (0 .. {len(board_points) - 1})")
    if len(corners) == 0:
        raise InvalidValue("corners", "no corners")
    return corners, board_points


def check_stack(value: Any, name: str, shape: tuple[int, ...], count: int | None = None) -> np.ndarray:
    """``value`` as a finite float64 stack ``(M, *shape)`` (``M == count`` when given), or InvalidValue."""
    array = np.asarray(value, dtype=np.float64)
    wrong_count = count is not None and len(array) != count
    if array.ndim != len(shape) + 1 or array.shape[1:] != shape or wrong_count:
        want = f"({count if count is not None else 'M'}, {', '.join(map(str, shape))})"
        raise InvalidValue(name, f"expected shape {want}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return array


def image_index(corners: Points2D) -> np.ndarray:
    """The image each corner was seen in (all on image 0 when ``corners.view`` is None)."""
    return corners.view if corners.view is not None else np.zeros(len(corners), dtype=np.int64)


def views_of(corners: Points2D) -> tuple[np.ndarray, np.ndarray]:
    """Sorted image indices of the views and, per corner, its position in that list."""
    views, position = np.unique(image_index(corners), return_inverse=True)
    return views, position.ravel()


@dataclass(frozen=True)
class Observations:
    """The corners sorted by view (stable within a view), each with what it observes.

    ``pixels`` ``(n, 2)`` detected positions, ``points`` ``(n, 3)`` the board corners they observe,
    ``position`` ``(n,)`` each one's view as an index into ``views``, ``image`` ``(n,)`` its image
    index, ``ids`` ``(n,)`` its board corner; ``views`` ``(M,)`` the sorted unique image indices.
    """

    pixels: np.ndarray
    points: np.ndarray
    position: np.ndarray
    image: np.ndarray
    ids: np.ndarray
    views: np.ndarray

    @classmethod
    def of(cls, corners: Points2D, board_points: np.ndarray, count: int | None = None) -> Observations:
        """Sort checked ``corners`` by view; ``count`` is the number of views the poses are for."""
        views, position = views_of(corners)
        if count is not None and len(views) != count:
            raise InvalidValue("corners", f"corners lie on {len(views)} views but the poses are for {count}")
        order = np.argsort(position, kind="stable")
        ids = np.asarray(corners.ids)
        return cls(corners.xy[order], board_points[ids[order]], position[order], image_index(corners)[order],
                   ids[order], views)

    def __len__(self) -> int:
        return len(self.pixels)


__all__ = ["Observations", "check_corners", "check_stack", "image_index", "views_of"]
