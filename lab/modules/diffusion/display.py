"""How samples are drawn: points as a point cloud (2D at z = 0), digits as one grid image."""

from __future__ import annotations

import math

import numpy as np

from lab.core import Image, PointCloud
from lab.modules.diffusion.values import DIGIT_SHAPE, TRACE_DIGITS


def as_3d(x: np.ndarray) -> np.ndarray:
    """``(N, 2)`` or ``(N, 3)`` points as ``(N, 3)`` float64 (2D points at z = 0)."""
    x = np.asarray(x, dtype=np.float64)
    return x if x.shape[1] == 3 else np.concatenate([x, np.zeros((len(x), 3 - x.shape[1]))], axis=1)


def digit_grid(x: np.ndarray, *, columns: int = 10, gap: int = 1) -> Image:
    """Flattened 8 x 8 digits ``(N, 64)`` in [0, 1] as one grid image: ``columns`` a row, ``gap`` px apart."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0, 1).reshape(-1, *DIGIT_SHAPE)
    rows = max(1, math.ceil(len(x) / columns))
    h, w = DIGIT_SHAPE
    grid = np.zeros((rows * (h + gap) + gap, columns * (w + gap) + gap), dtype=np.float32)
    for i, digit in enumerate(x):
        r, c = divmod(i, columns)
        grid[gap + r * (h + gap):gap + r * (h + gap) + h, gap + c * (w + gap):gap + c * (w + gap) + w] = digit
    return Image(grid, name="digits")


def display(x: np.ndarray, kind: str) -> PointCloud | Image:
    """Samples ``(N, D)`` in data units as the value the viewer draws: digits a grid of the first 100."""
    if kind == "digits":
        return digit_grid(x[:TRACE_DIGITS])
    return PointCloud(as_3d(x))


__all__ = ["as_3d", "digit_grid", "display"]
