"""Stereo test pairs shared by tests/modules/test_stereo*.py: a texture and the same texture shifted by a
known disparity."""

import numpy as np
from scipy import ndimage

from lab.core import Image


def shifted_pair(disparity: float, *, height: int = 40, width: int = 80,
                 seed: int = 0) -> tuple[Image, Image]:
    """A smooth random texture and the same texture seen ``disparity`` px further left
    (left(x) = right(x - d))."""
    rng = np.random.default_rng(seed)
    base = ndimage.gaussian_filter(rng.random((height, width + 40)), 1.2)
    base = (base - base.min()) / (base.max() - base.min())
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    left = ndimage.map_coordinates(base, [yy, xx + 20], order=3, mode="nearest")
    right = ndimage.map_coordinates(base, [yy, xx + 20 + disparity], order=3, mode="nearest")
    return Image(np.clip(left, 0, 1).astype(np.float32)), Image(np.clip(right, 0, 1).astype(np.float32))
