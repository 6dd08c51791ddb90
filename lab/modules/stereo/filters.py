"""Cleaning a disparity map: median, uniqueness, peak removal, hole filling; and its colour image.

Helpers of :func:`lab.modules.stereo.filter_disparity` (Hirschmüller 2008, sections 4.1-4.4;
OpenCV's ``uniquenessRatio``, ``speckleWindowSize``/``speckleRange``). A hole is :data:`HOLE` (-1).
"""

from __future__ import annotations

import numpy as np

from lab.core import Image, InvalidValue
from lab.modules.stereo.lean import RowWinners
from lab.modules.stereo.winners import best_two_costs

#: Disparities of the final map that mark a hole.
HOLE = -1.0


def median_filter(disparity: np.ndarray, size: int) -> np.ndarray:
    """A ``size x size`` median filter of a float64 map (``cv2.medianBlur`` in float32; 1: the map itself)."""
    import cv2

    if size == 1:
        return disparity
    return cv2.medianBlur(disparity.astype(np.float32), int(size)).astype(np.float64)


def unique_winners(volume: np.ndarray | RowWinners, uniqueness: float) -> np.ndarray:
    """``(H, W)`` bool: the winner's cost is below ``1 - uniqueness`` times the best cost two or more
    disparities away (:func:`best_two_costs`, or those a volume aggregated by rows kept; OpenCV's
    ``uniquenessRatio``)."""
    best, second = (volume.best, volume.second) if isinstance(volume, RowWinners) else best_two_costs(volume)
    return best < (1.0 - uniqueness) * second


def remove_peaks(disparity: np.ndarray, *, max_size: int, max_difference: float) -> np.ndarray:
    """Turn small islands of disparity into holes: 4-connected regions whose neighbours differ by at most
    ``max_difference`` px and that hold at most ``max_size`` pixels (Hirschmüller 2008, section 4.3,
    "removal of peaks"). Uses ``cv2.filterSpeckles`` on disparities in 1/16 px. Returns a new map."""
    import cv2

    d = np.asarray(disparity, dtype=np.float64)
    if max_size <= 0:
        return d.copy()
    if d.size and d.max() >= 2047:
        raise InvalidValue("disparity", "peak removal handles disparities below 2047 px")
    fixed = np.where(d >= 0, np.rint(d * 16.0), -16).astype(np.int16)
    cv2.filterSpeckles(fixed, -16, int(max_size), round(max_difference * 16.0))
    return np.where(fixed == -16, HOLE, d)


def fill_holes(disparity: np.ndarray) -> np.ndarray:
    """Fill each hole (-1) with the lower of the nearest valid disparities to its left and right on its row.

    The lower disparity is the farther surface: holes are mostly occlusions, which show the
    background (Hirschmüller 2008, section 4.4). A row without any valid pixel stays a hole.
    Returns a new ``(H, W)`` float64 map.
    """
    d = np.asarray(disparity, dtype=np.float64)
    valid = d >= 0
    H, W = d.shape
    columns = np.broadcast_to(np.arange(W), (H, W))
    rows = np.arange(H)[:, None]
    before = np.maximum.accumulate(np.where(valid, columns, -1), axis=1)
    after = np.minimum.accumulate(np.where(valid, columns, W)[:, ::-1], axis=1)[:, ::-1]
    from_left = np.where(before >= 0, d[rows, np.clip(before, 0, W - 1)], np.inf)
    from_right = np.where(after < W, d[rows, np.clip(after, 0, W - 1)], np.inf)
    fill = np.minimum(from_left, from_right)
    return np.where(valid, d, np.where(np.isfinite(fill), fill, HOLE))


def colorize_disparity(disparity: np.ndarray, *, max_disparity: float | None = None,
                       name: str = "disparity") -> Image:
    """A disparity map as a colour image (OpenCV's turbo colormap: far blue, near red); holes black."""
    import cv2

    d = np.asarray(disparity, dtype=np.float64)
    valid = d >= 0
    top = float(max_disparity) if max_disparity else (float(d[valid].max()) if valid.any() else 1.0)
    levels = np.clip(np.where(valid, d, 0.0) / max(top, 1e-9) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(levels, cv2.COLORMAP_TURBO)[:, :, ::-1]
    rgb = np.where(valid[:, :, None], rgb, 0).astype(np.uint8)
    return Image(rgb, name=name)
