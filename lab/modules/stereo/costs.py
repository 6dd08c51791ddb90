"""Matching costs: every window cost as a box filter of a per-pixel term, census and rank, NCC in float64.

What :func:`lab.modules.stereo.cost_volume` computes, cost by cost (Scharstein and Szeliski 2002,
section 3.1; Zabih and Woodfill 1994). A window sum is a box filter applied to each disparity
slice, computed with running sums in O(1) per window (:func:`box_mean`), never by a loop over the
window's pixels. Costs are normalized per window pixel so that one SGM penalty suits every cost
and window. The loops are the Numba kernels of :mod:`._kernels`; their readable versions are in
:mod:`.reference`.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np

from lab.core.kernels import bands, in_parallel
from lab.modules.stereo._checks import check_window
from lab.modules.stereo._kernels import (_box_columns_kernel, _box_rows_kernel, _census_costs_kernel,
                                         _census_transform_kernel, _hamming_costs_kernel,
                                         _ncc_from_moments_kernel)

#: A matching cost :func:`cost_volume` knows, and all of them in order.
Cost = Literal["ssd", "nssd", "sad", "zsad", "ncc", "rank", "census"]
COSTS: tuple[str, ...] = get_args(Cost)

#: Entries of the float64 volumes :func:`ncc_costs` builds at once (a few disparities at a time).
NCC_CHUNK_ENTRIES = 2**22

#: A window whose gray-level variance is below this is flat: its NCC is 0 (its cost 1). One gray
#: level of an 8-bit image in one pixel of a 7 x 7 window gives a variance of about 3e-7.
NCC_FLAT_VARIANCE = 1e-10


# ----------------------------------------------------------------------------------------------------
# Box filtering: the O(1)-per-window sum
# ----------------------------------------------------------------------------------------------------
def box_filter_inplace(volume: np.ndarray, window: int, factor: float) -> np.ndarray:
    """``factor`` times the window sums of a C-contiguous float32 or float64 ``(H, W, D)`` volume, in place.

    Separable running sums, O(1) work per window whatever its size: along each row, then down the
    columns (float64 accumulators); bands of rows, then of columns, run on the thread pool.
    """
    if window == 1:
        if factor != 1.0:
            volume *= volume.dtype.type(factor)
        return volume
    H, W, _ = volume.shape
    radius = window // 2
    in_parallel(_box_rows_kernel, [(volume, radius, y0, y1) for y0, y1 in bands(H)])
    in_parallel(_box_columns_kernel, [(volume, radius, float(factor), x0, x1) for x0, x1 in bands(W)])
    return volume


def box_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean over each ``window x window`` neighbourhood, borders replicated, per slice of ``(H, W)`` or
    ``(H, W, D)``.

    The aggregation of every window cost: running sums make it O(1) per window (fast kernel);
    :func:`box_mean_reference` computes the same with a summed-area table. Corresponds to
    ``cv2.boxFilter(slice, -1, (window, window), normalize=True, borderType=cv2.BORDER_REPLICATE)``
    on each slice. Returns a new float32 array of the input's shape.
    """
    window = check_window(window)
    array = np.asarray(values, dtype=np.float32)
    volume = np.array(array[:, :, None] if array.ndim == 2 else array, dtype=np.float32, order="C", copy=True)
    box_filter_inplace(volume, window, 1.0 / (window * window))
    return volume[:, :, 0] if array.ndim == 2 else volume


def box_mean64(values: np.ndarray, window: int) -> np.ndarray:
    """:func:`box_mean` in float64 of an ``(H, W)`` or ``(H, W, D)`` array (a new array)."""
    volume = np.array(values[:, :, None] if values.ndim == 2 else values, dtype=np.float64, order="C",
                      copy=True)
    box_filter_inplace(volume, window, 1.0 / (window * window))
    return volume[:, :, 0] if values.ndim == 2 else volume


# ----------------------------------------------------------------------------------------------------
# Census and rank transforms
# ----------------------------------------------------------------------------------------------------
def census_words(window: int) -> int:
    return -(-(window * window - 1) // 64)


def census_transform(gray: np.ndarray, window: int) -> np.ndarray:
    """Census bit strings: bit ``k`` of pixel ``p`` is 1 when its ``k``-th neighbour (raster order over the
    ``window x window`` neighbourhood, centre skipped, borders replicated) is darker than ``p``.

    Returns ``(H, W, words)`` uint64, ``words = ceil((window^2 - 1) / 64)``; bit ``k`` is bit
    ``k mod 64`` of word ``k // 64``. Fast kernel; :func:`census_transform_reference` is the oracle.
    Reference: Zabih and Woodfill (1994), section 3.
    """
    window = check_window(window, "census")
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    return _census_transform_kernel(gray, window // 2, census_words(window))


def hamming_costs(codes_left: np.ndarray, codes_right: np.ndarray, disparities: int) -> np.ndarray:
    """Hamming distances ``(H, W, D)`` float32 between left census strings and the right ones ``d`` columns to
    the left (column 0 replicated): ``popcount(c_l(x) XOR c_r(x - d))``. Fast kernel (bands of rows on
    the thread pool); the oracle is :func:`hamming_costs_reference`."""
    codes_left, codes_right = np.ascontiguousarray(codes_left), np.ascontiguousarray(codes_right)
    H, W, _ = codes_left.shape
    out = np.empty((H, W, int(disparities)), np.float32)
    in_parallel(_hamming_costs_kernel, [(codes_left, codes_right, out, y0, y1) for y0, y1 in bands(H)])
    return out


def census_costs(gray_left: np.ndarray, gray_right: np.ndarray, disparities: int, window: int) -> np.ndarray:
    """The census cost volume ``(H, W, D)`` float32: the Hamming distances of the census strings over the
    ``window`` (:func:`census_transform`), averaged over the window and divided by the ``window^2 - 1``
    bits of a string, so costs lie in [0, 1].

    Equals ``box_mean(hamming_costs(c_l, c_r, D), window) / (window^2 - 1)`` bit for bit; one fused
    kernel (:func:`_census_costs_kernel`, bands of rows on the thread pool) never writes the
    per-pixel Hamming volume.
    """
    window = check_window(window, "census")
    codes_left = census_transform(gray_left, window)
    codes_right = census_transform(gray_right, window)
    H, W, _ = codes_left.shape
    out = np.empty((H, W, int(disparities)), np.float32)
    factor = 1.0 / (window * window * (window * window - 1))
    in_parallel(_census_costs_kernel, [(codes_left, codes_right, window // 2, factor, out, y0, y1, 0)
                                          for y0, y1 in bands(H)])
    return out


def rank_transform(gray: np.ndarray, window: int) -> np.ndarray:
    """Rank of each pixel in its ``window x window`` neighbourhood: how many neighbours are darker,
    ``(H, W)`` int.

    Borders replicated. Reference: Zabih and Woodfill (1994), section 2.
    """
    window = check_window(window, "rank")
    r = window // 2
    H, W = gray.shape
    padded = np.pad(np.asarray(gray, dtype=np.float32), r, mode="edge")
    rank = np.zeros((H, W), np.int32)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy or dx:
                rank += padded[r + dy:r + dy + H, r + dx:r + dx + W] < gray
    return rank


# ----------------------------------------------------------------------------------------------------
# Window costs on the right image shifted by every disparity
# ----------------------------------------------------------------------------------------------------
def shifted_columns(width: int, disparities: int) -> np.ndarray:
    """``(W, D)`` right-image column seen by left column ``x`` at disparity ``d``: ``max(x - d, 0)``."""
    return np.maximum(np.arange(width)[:, None] - np.arange(disparities)[None, :], 0)


def shifted_right(values: np.ndarray, disparities: int) -> np.ndarray:
    """The right image (or any per-pixel map) shifted by every disparity: ``(H, W) -> (H, W, D)``,
    ``out[y, x, d] = values[y, max(x - d, 0)]``."""
    return np.ascontiguousarray(values[:, shifted_columns(values.shape[1], disparities)])


def _pixel_volume(cost: str, a: np.ndarray, b: np.ndarray, disparities: int, window: int) -> np.ndarray:
    """The per-pixel part of the costs that are box means of a per-pixel term (SSD, SAD, ZSAD, rank)."""
    if cost == "rank":
        a = rank_transform(a, window).astype(np.float32) / np.float32(window * window - 1)
        b = rank_transform(b, window).astype(np.float32) / np.float32(window * window - 1)
    elif cost == "zsad":
        a = a - box_mean(a, window)
        b = b - box_mean(b, window)
    difference = a[:, :, None] - shifted_right(b, disparities)
    return np.square(difference) if cost == "ssd" else np.abs(difference)


def window_costs(cost: str, a: np.ndarray, b: np.ndarray, disparities: int, window: int) -> np.ndarray:
    """SSD, SAD, ZSAD or rank costs ``(H, W, D)`` float32: the box mean of the per-pixel term over the
    window."""
    per_pixel = np.ascontiguousarray(_pixel_volume(cost, a, b, disparities, window), dtype=np.float32)
    return box_filter_inplace(per_pixel, window, 1.0 / (window * window))


def nssd_costs(a: np.ndarray, b: np.ndarray, disparities: int, window: int) -> np.ndarray:
    """Normalized SSD ``sum (a - b)^2 / sqrt(sum a^2 sum b^2)`` ``(H, W, D)`` float32, from box means of
    products computed in place so that at most three volumes live at once."""
    b_shifted = shifted_right(b, disparities)
    energy_b = box_filter_inplace(np.square(b_shifted), window, 1.0 / (window * window))
    squared = np.subtract(a[:, :, None], b_shifted, out=b_shifted)
    squared = box_filter_inplace(np.square(squared, out=squared), window, 1.0 / (window * window))
    energy_b *= box_mean(a * a, window)[:, :, None]
    np.sqrt(energy_b, out=energy_b)
    return np.divide(squared, np.maximum(energy_b, np.float32(1e-12), out=energy_b), out=squared)


def ncc_costs(a: np.ndarray, b: np.ndarray, disparities: int, window: int) -> np.ndarray:
    """``1 - NCC`` for every disparity, the window moments in float64, a few disparities at a time.

    ``var = mean(x^2) - mean(x)^2`` cancels badly in float32 where a window is nearly flat (a
    variance of 1e-6 next to a mean square of 0.25), so the moments are box means of float64
    slices (:func:`box_filter_inplace`); the result is rounded to float32 once. A window with a
    variance below :data:`NCC_FLAT_VARIANCE` (in either image) gets NCC 0.
    """
    H, W = a.shape
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    mean_a = box_mean64(a, window)
    var_a = np.maximum(box_mean64(a * a, window) - mean_a * mean_a, 0.0)
    columns = shifted_columns(W, disparities)
    out = np.empty((H, W, disparities), np.float32)
    chunk = max(1, min(disparities, NCC_CHUNK_ENTRIES // max(H * W, 1)))
    for d0 in range(0, disparities, chunk):
        b_shifted = b[:, columns[:, d0:d0 + chunk]]  # (H, W, k) float64, C-contiguous
        mean_bb = box_filter_inplace(b_shifted * b_shifted, window, 1.0 / (window * window))
        mean_ab = box_filter_inplace(np.multiply(a[:, :, None], b_shifted), window, 1.0 / (window * window))
        mean_b = box_filter_inplace(b_shifted, window, 1.0 / (window * window))
        _ncc_from_moments_kernel(mean_a, var_a, mean_b, mean_bb, mean_ab, NCC_FLAT_VARIANCE, out, d0)
    return out
