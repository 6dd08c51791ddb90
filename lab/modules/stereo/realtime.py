"""Real-time block matching: winner-take-all integer SAD over square windows, for video-rate stereo.

The local method of Scharstein and Szeliski (2002), section 3 (matching cost: absolute differences;
aggregation: a square window; optimization: winner-take-all), as the real-time systems of the
late 1990s ran it (SRI's SVS, Point Grey's Triclops, the PARTS FPGA: 320 x 240, 32 disparities,
20 to 42 frames per second) and as ``cv2.StereoBM`` does without its prefilter and post-filters.
Running sums make the work O(H W D) whatever the window (Faugeras et al. 1993, "Real time
correlation-based stereo", INRIA RR-2013, section 3): a column sum per pixel and disparity is updated
from row to row (one row enters, one leaves), and each window sum from column to column.
The kernel is in :mod:`._kernels`; :func:`~lab.modules.stereo.reference.block_match_realtime_reference`
is its readable oracle.

The pipeline's face of the same math is ``cost_volume(cost="sad", window=block)`` with
``aggregate_costs(method="none")`` and :func:`~lab.modules.stereo.winner_take_all`, which keeps the
volume for the viewer (and replicates borders instead of leaving them invalid).
"""

from __future__ import annotations

import numpy as np

from lab.core import InvalidControl, InvalidValue
from lab.core.kernels import bands, in_parallel
from lab.modules.stereo._checks import check_max_disparity, check_window
from lab.modules.stereo._kernels import _block_match_realtime_kernel

#: The disparity of a pixel whose window leaves the image (at any disparity): a hole, as in :mod:`.filters`.
INVALID = -1


def gray_levels(image: np.ndarray, name: str) -> np.ndarray:
    """An ``(H, W)`` grey image as uint8 levels: uint8 as is, floats in [0, 1] scaled by 255 and rounded."""
    array = np.asarray(image)
    if array.ndim != 2:
        raise InvalidValue(name, f"expected a grey image (H, W), got shape {array.shape}")
    if array.dtype == np.uint8:
        return np.ascontiguousarray(array)
    if array.dtype.kind != "f":
        raise InvalidValue(name, f"expected uint8 levels or floats in [0, 1], got dtype {array.dtype}")
    if array.size and not (np.isfinite(array).all() and array.min() >= 0.0 and array.max() <= 1.0):
        raise InvalidValue(name, "float grey levels must lie in [0, 1] (the lab's Image convention); "
                                 "give 8-bit images as uint8")
    return np.rint(array * 255.0).astype(np.uint8)


def block_match_realtime(left: np.ndarray, right: np.ndarray, *, max_disparity: int = 31, block: int = 9,
                         parallel: bool = True) -> np.ndarray:
    """The disparity of every left pixel minimizing the sum of absolute differences over a square block.

    ``SAD(x, y, d) = sum_{|i|, |j| <= r} |L(x + j, y + i) - R(x + j - d, y + i)|`` on 8-bit levels
    (integers, so exact), ``r = block // 2``, for ``d = 0 .. max_disparity``; the winner is the
    smallest ``d`` of least SAD. Pixels where a window leaves the image at some disparity
    (``y < r``, ``y >= H - r``, ``x < r + max_disparity``, ``x >= W - r``) are :data:`INVALID`.

    Args:
        left, right: the rectified grey pair ``(H, W)``, uint8, or float in [0, 1] (rounded to
            8 bits).
        max_disparity: largest disparity searched, pixels (``max_disparity + 1`` levels; 31 is
            OpenCV's ``numDisparities=32``).
        block: side of the square window, odd.
        parallel: bands of rows on the lab's kernel thread pool; ``False`` runs one thread.

    Returns ``(H, W)`` int64 disparities, :data:`INVALID` outside the valid region.
    """
    a, b = gray_levels(left, "left"), gray_levels(right, "right")
    if a.shape != b.shape:
        raise InvalidValue("right", f"the two images differ in size: left is {a.shape}, right is {b.shape}")
    block = check_window(block)
    H, W = a.shape
    max_disparity = check_max_disparity(max_disparity, W)
    radius = block // 2
    if block > H or block + max_disparity > W:
        raise InvalidControl("block", f"a {block} x {block} window searching {max_disparity + 1} disparities "
                                      f"needs an image of at least {block + max_disparity} x {block} px; "
                                      f"this one is {W} x {H}")
    out = np.full((H, W), INVALID, np.int64)
    y0, y1 = radius, H - radius
    jobs = [(a, b, max_disparity, radius, out, y0 + s0, y0 + s1)
            for s0, s1 in bands(y1 - y0, parts=None if parallel else 1)]
    in_parallel(_block_match_realtime_kernel, jobs)
    return out
