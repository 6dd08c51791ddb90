"""Stereo disparity step by step: rectify, match, aggregate (SGM), pick, check, refine, filter, triangulate.

References: D. Scharstein and R. Szeliski, "A taxonomy and evaluation of dense two-frame stereo
correspondence algorithms", IJCV 47 (2002) (the four stages: matching cost, aggregation,
optimization, refinement; the bad-pixel metrics); H. Hirschmüller, "Stereo processing by semiglobal
matching and mutual information", IEEE TPAMI 30(2), 2008 (SGM, the left-right check, peak removal,
hole interpolation); R. Zabih and J. Woodfill, "Non-parametric local transforms for computing visual
correspondence", ECCV 1994 (rank and census); R. Szeliski, *Computer Vision: Algorithms and
Applications*, 2nd ed. (2022), chapter 12 (dense correspondence); Hartley & Zisserman, *Multiple View
Geometry*, 2nd ed., section 11.12 (rectification); J.-Y. Bouguet's rectification
(:mod:`lab.geometry.rectification`).

Conventions. Images are rectified: a point at column ``x`` of the left image is seen at column
``x - d`` of the right one, on the same row, with disparity ``d >= 0`` (pixels). A cost volume is a
float32 array ``(H, W, D)``: ``volume[y, x, d]`` is the cost of matching left pixel ``(x, y)`` with
right pixel ``(x - d, y)``, for ``d = 0 .. max_disparity`` (``D = max_disparity + 1``); right pixels
left of the image take the value of its first column (border replicated), as do windows reaching
over any border. Costs are normalized per window pixel so that one penalty suits every cost and
window (section "Matching costs" below).

State names (float64 unless said):
    left_raw, right_raw   Image              the photos as taken (dataset)
    calibration           StereoCalibration  K, distortion, R, T of the pair (dataset)
    left, right           Image              the rectified pair
    K                     (3, 3)             camera matrix of the rectified left image
    baseline              float              distance between the camera centres, metres
    disparity_offset      float              cx_right - cx_left of the rectified pair, pixels
                                             (0 after our rectification; Middlebury's ``doffs``)
    cost_volume           (H, W, D) float32  matching costs (kept in state: at most 2**26 entries)
    aggregated_cost       (H, W, D) float32  costs after aggregation (SGM), or the same array
    disparity_wta         (H, W) int64       winner-take-all disparity of every pixel
    consistent            (H, W) bool        pixels that pass the left-right check
    disparity_subpixel    (H, W)             disparity refined by a parabola, every pixel
    disparity             (H, W)             final disparity in pixels; -1 marks a hole (no NaN)
    disparity_image       Image              the disparity colour-mapped (turbo), holes black
    depth                 (H, W)             Z = f B / (d + disparity_offset) in metres; 0 in holes
    depth_uncertainty     (H, W)             u_z = Z^2 u_d / (f B), metres; 0 in holes
    points3d              PointCloud         pixels with a depth, in the rectified left camera frame, coloured
    cameras               Cameras            the rectified pair (left at the origin, right at x = baseline)

Ground truth (``Session.truth``, never a step input): ``disparity`` (H, W) with -1 where unknown,
``depth`` (H, W) with 0 where unknown, ``points`` (N, 3) scene points in the left raw camera frame
(synthetic unrectified pairs, to measure rectification). :func:`error_map` and
:func:`cost_curves` build the viewer's error map and the cost curves of a clicked pixel.

Fast kernels (Numba) each have a slow readable reference (``*_reference``) that the tests use as
their oracle.
"""

from __future__ import annotations

import os
from typing import Annotated, Any, Literal

import numba
import numpy as np

from lab.core.step import step_result, Warnings
from lab.core import Cameras, Curve, Image, InvalidControl, InvalidValue, Pipeline, PointCloud, Range, metric
from lab.data.stereo import folder, motorcycle, synthetic
from lab.geometry.camera import as_intrinsics
from lab.geometry.rectification import StereoCalibration, rectification_map, rectify_pixels, stereo_rectify
from lab.geometry.rotations import rotation_angle_deg

#: Matching costs :func:`cost_volume` knows.
COSTS: tuple[str, ...] = ("ssd", "nssd", "sad", "zsad", "ncc", "rank", "census")
Cost = Literal["ssd", "nssd", "sad", "zsad", "ncc", "rank", "census"]

#: Largest cost volume (H * W * D entries) a step builds: 2**26 float32 entries are 256 MiB.
MAX_VOLUME_ENTRIES = 2**26

#: Disparities of the final map that mark a hole.
HOLE = -1.0


def _kernel(func: Any) -> Any:
    """``numba.njit`` without the GIL, cached on disk where the package folder is writable (else compiled
    once per process)."""
    try:
        return numba.njit(cache=True, nogil=True)(func)
    except RuntimeError:  # no writable cache location (a read-only install, a sandbox)
        return numba.njit(nogil=True)(func)


def _workers() -> int:
    """Threads the kernels use: the CPUs this process may run on (OpenCV's SGBM uses them all too)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


_POOL: Any = None


def _forget_pool() -> None:
    """A forked child has none of its parent's threads: it builds its own pool when it needs one."""
    global _POOL
    _POOL = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _in_parallel(function: Any, jobs: list[tuple[Any, ...]]) -> None:
    """Run ``function(*job)`` for every job, on a thread pool (the kernels release the GIL)."""
    global _POOL
    if len(jobs) == 1:
        function(*jobs[0])
        return
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = ThreadPoolExecutor(max_workers=_workers(), thread_name_prefix="stereo")
    for future in [_POOL.submit(function, *job) for job in jobs]:
        future.result()


def _bands(count: int) -> list[tuple[int, int]]:
    """Split ``range(count)`` into one contiguous band per worker."""
    parts = max(1, min(_workers(), count))
    edges = np.linspace(0, count, parts + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


# ----------------------------------------------------------------------------------------------------
# Input checks
# ----------------------------------------------------------------------------------------------------
def _check_pair(left: Any, right: Any, *, names: tuple[str, str] = ("left", "right")) -> tuple[Image, Image]:
    for value, name in zip((left, right), names):
        if not isinstance(value, Image):
            raise InvalidValue(name, f"expected an Image, got {type(value).__name__}")
    if left.pixels.shape[:2] != right.pixels.shape[:2]:
        raise InvalidValue(names[1], f"the two images differ in size: {names[0]} is {left.width} x {left.height}, "
                                     f"{names[1]} is {right.width} x {right.height}; a stereo pair needs one size")
    return left, right


def _check_window(window: int, cost: str = "sad") -> int:
    window = int(window)
    if window < 1 or window % 2 == 0:
        raise InvalidControl("window", f"must be an odd number of pixels (1, 3, 5 ...), got {window}")
    if cost in ("rank", "census") and window < 3:
        raise InvalidControl("window", f"{cost} compares each pixel with its neighbours: the window must be at least 3")
    return window


def _check_max_disparity(max_disparity: int, width: int) -> int:
    max_disparity = int(max_disparity)
    if max_disparity < 1:
        raise InvalidControl("max_disparity", f"must be at least 1 pixel, got {max_disparity}")
    if max_disparity >= width:
        raise InvalidControl("max_disparity", f"the disparity range (0 to {max_disparity} px) is larger than the "
                                              f"image, which is {width} px wide; use at most {width - 1}")
    return max_disparity


def _check_volume(volume: Any, name: str, *, finite: bool = True) -> np.ndarray:
    array = np.asarray(volume)
    if array.ndim != 3 or array.shape[2] < 1:
        raise InvalidValue(name, f"a cost volume is (H, W, D), got shape {array.shape}")
    if array.dtype.kind not in "fiu":
        raise InvalidValue(name, f"a cost volume holds numbers, got dtype {array.dtype}")
    array = np.ascontiguousarray(array, dtype=np.float32)
    if finite and array.size and not (np.isfinite(array.min()) and np.isfinite(array.max())):  # NaN propagates
        raise InvalidValue(name, "contains NaN or infinite costs")
    return array


def _check_map(value: Any, name: str, shape: tuple[int, int], *, kind: str = "f") -> np.ndarray:
    array = np.asarray(value)
    if array.shape != shape:
        raise InvalidValue(name, f"expected shape {shape} (the cost volume's H, W), got {array.shape}")
    if kind == "b":
        if array.dtype != bool:
            raise InvalidValue(name, f"expected a boolean mask, got dtype {array.dtype}")
        return array
    if array.dtype.kind not in "fiu":
        raise InvalidValue(name, f"expected numbers, got dtype {array.dtype}")
    array = array.astype(np.float64)
    if not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries; mark holes with -1")
    return array


def _entries_check(height: int, width: int, disparities: int) -> None:
    entries = height * width * disparities
    if entries > MAX_VOLUME_ENTRIES:
        raise InvalidControl("max_disparity", f"the cost volume would hold {height} x {width} x {disparities} = "
                                              f"{entries:,} costs ({entries * 4 / 2**20:.0f} MiB), more than the "
                                              f"{MAX_VOLUME_ENTRIES:,} allowed; lower max_disparity or use smaller "
                                              "images (the datasets' downsample option)")


# ----------------------------------------------------------------------------------------------------
# Box filtering: the O(1)-per-window sum
# ----------------------------------------------------------------------------------------------------
@_kernel
def _box_rows_kernel(volume, radius, y0, y1):
    """In place, rows ``y0:y1``: each ``volume[y, :, d]`` becomes its running sums over ``2 radius + 1``
    columns (borders replicated), read from a copy of the row."""
    H, W, D = volume.shape
    line = np.empty((W, D), volume.dtype)
    sums = np.zeros(D, np.float64)
    for y in range(y0, y1):
        row = volume[y]
        for x in range(W):
            for d in range(D):
                line[x, d] = row[x, d]
        for d in range(D):
            sums[d] = 0.0
        for k in range(-radius, radius + 1):
            column = min(max(k, 0), W - 1)
            for d in range(D):
                sums[d] += line[column, d]
        for x in range(W):
            enter = min(x + radius + 1, W - 1)
            leave = max(x - radius, 0)
            for d in range(D):
                row[x, d] = sums[d]
                sums[d] += line[enter, d] - line[leave, d]


@_kernel
def _box_columns_kernel(volume, radius, factor, x0, x1):
    """In place, columns ``x0:x1``: ``factor`` times the running sums over ``2 radius + 1`` rows (borders
    replicated), the rows that leave the window kept in a ring of the last ``2 radius + 2``."""
    H, W, D = volume.shape
    size = 2 * radius + 2
    ring = np.empty((size, x1 - x0, D), volume.dtype)
    acc = np.zeros((x1 - x0, D), np.float64)
    for k in range(-radius, radius + 1):
        source = volume[min(max(k, 0), H - 1)]
        for x in range(x0, x1):
            for d in range(D):
                acc[x - x0, d] += source[x, d]
    for y in range(H):
        row = volume[y]
        saved = ring[y % size]
        for x in range(x0, x1):
            for d in range(D):
                saved[x - x0, d] = row[x, d]
                row[x, d] = acc[x - x0, d] * factor  # rounded to the volume's dtype
        enter = min(y + radius + 1, H - 1)
        leaving = ring[max(y - radius, 0) % size]
        if enter > y:
            entering = volume[enter]
            for x in range(x0, x1):
                for d in range(D):
                    acc[x - x0, d] += entering[x, d] - leaving[x - x0, d]
        else:
            entering = ring[enter % size]
            for x in range(x0, x1):
                for d in range(D):
                    acc[x - x0, d] += entering[x - x0, d] - leaving[x - x0, d]


def _box_filter_inplace(volume: np.ndarray, window: int, factor: float) -> np.ndarray:
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
    _in_parallel(_box_rows_kernel, [(volume, radius, y0, y1) for y0, y1 in _bands(H)])
    _in_parallel(_box_columns_kernel, [(volume, radius, float(factor), x0, x1) for x0, x1 in _bands(W)])
    return volume


def box_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean over each ``window x window`` neighbourhood, borders replicated, per slice: ``(H, W)`` or ``(H, W, D)``.

    The aggregation of every window cost: running sums make it O(1) per window (fast kernel);
    :func:`box_mean_reference` computes the same with a summed-area table. Corresponds to
    ``cv2.boxFilter(slice, -1, (window, window), normalize=True, borderType=cv2.BORDER_REPLICATE)``
    on each slice. Returns a new float32 array of the input's shape.
    """
    window = _check_window(window)
    array = np.asarray(values, dtype=np.float32)
    volume = np.array(array[:, :, None] if array.ndim == 2 else array, dtype=np.float32, order="C", copy=True)
    _box_filter_inplace(volume, window, 1.0 / (window * window))
    return volume[:, :, 0] if array.ndim == 2 else volume


def box_mean_reference(values: np.ndarray, window: int) -> np.ndarray:
    """:func:`box_mean` by a summed-area table (Crow 1984): pad by replication, cumulative sums along
    rows and columns, and each window's sum from four table entries,
    ``S(y2, x2) - S(y1, x2) - S(y2, x1) + S(y1, x1)``."""
    array = np.asarray(values, dtype=np.float64)
    r = window // 2
    pad = [(r, r), (r, r)] + [(0, 0)] * (array.ndim - 2)
    padded = np.pad(array, pad, mode="edge")
    table = np.zeros((padded.shape[0] + 1, padded.shape[1] + 1) + padded.shape[2:])
    table[1:, 1:] = padded.cumsum(axis=0).cumsum(axis=1)
    H, W = array.shape[:2]
    sums = table[window:window + H, window:window + W] - table[:H, window:window + W] \
        - table[window:window + H, :W] + table[:H, :W]
    return (sums / (window * window)).astype(np.float32)


# ----------------------------------------------------------------------------------------------------
# Census and rank transforms
# ----------------------------------------------------------------------------------------------------
def _census_words(window: int) -> int:
    return -(-(window * window - 1) // 64)


@_kernel
def _census_kernel(gray, radius, words):
    H, W = gray.shape
    padded = np.empty((H + 2 * radius, W + 2 * radius), np.float32)
    for y in range(H + 2 * radius):
        source = min(max(y - radius, 0), H - 1)
        for x in range(W + 2 * radius):
            padded[y, x] = gray[source, min(max(x - radius, 0), W - 1)]
    out = np.zeros((H, W, words), np.uint64)
    for y in range(H):
        bit = 0
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                if dy == 0 and dx == 0:
                    continue
                word = bit >> 6
                mask = np.uint64(1) << np.uint64(bit & 63)
                neighbours = padded[y + radius + dy]
                for x in range(W):
                    if neighbours[x + radius + dx] < gray[y, x]:
                        out[y, x, word] |= mask
                bit += 1
    return out


def census_transform(gray: np.ndarray, window: int) -> np.ndarray:
    """Census bit strings: bit ``k`` of pixel ``p`` is 1 when its ``k``-th neighbour (raster order over the
    ``window x window`` neighbourhood, centre skipped, borders replicated) is darker than ``p``.

    Returns ``(H, W, words)`` uint64, ``words = ceil((window^2 - 1) / 64)``; bit ``k`` is bit
    ``k mod 64`` of word ``k // 64``. Fast kernel; :func:`census_transform_reference` is the oracle.
    Reference: Zabih and Woodfill (1994), section 3.
    """
    window = _check_window(window, "census")
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    return _census_kernel(gray, window // 2, _census_words(window))


def census_transform_reference(gray: np.ndarray, window: int) -> np.ndarray:
    """:func:`census_transform` with one shifted comparison of the whole image per neighbour."""
    r = window // 2
    H, W = gray.shape
    padded = np.pad(np.asarray(gray, dtype=np.float32), r, mode="edge")
    out = np.zeros((H, W, _census_words(window)), np.uint64)
    bit = 0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx == 0:
                continue
            darker = padded[r + dy:r + dy + H, r + dx:r + dx + W] < gray
            out[:, :, bit // 64] |= darker.astype(np.uint64) << np.uint64(bit % 64)
            bit += 1
    return out


@_kernel
def _popcount(value):
    value = value - ((value >> np.uint64(1)) & np.uint64(0x5555555555555555))
    value = (value & np.uint64(0x3333333333333333)) + ((value >> np.uint64(2)) & np.uint64(0x3333333333333333))
    value = (value + (value >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((value * np.uint64(0x0101010101010101)) >> np.uint64(56))


@_kernel
def _hamming_kernel(codes_left, codes_right, out, y0, y1):
    H, W, words = codes_left.shape
    disparities = out.shape[2]
    counts = np.zeros(disparities, np.int64)
    reversed_row = np.empty((words, W + disparities), np.uint64)
    for y in range(y0, y1):
        # reversed_row[w, (W - 1 - x) + d] = codes_right[y, max(x - d, 0), w]: the d loop reads forward
        for w in range(words):
            for j in range(W + disparities):
                reversed_row[w, j] = codes_right[y, max(W - 1 - j, 0), w]
        for x in range(W):
            base = W - 1 - x
            for d in range(disparities):
                counts[d] = 0
            for w in range(words):
                code = codes_left[y, x, w]
                for d in range(disparities):
                    counts[d] += _popcount(code ^ reversed_row[w, base + d])
            for d in range(disparities):
                out[y, x, d] = np.float32(counts[d])


def hamming_costs(codes_left: np.ndarray, codes_right: np.ndarray, disparities: int) -> np.ndarray:
    """Hamming distances ``(H, W, D)`` float32 between left census strings and the right ones ``d`` columns to
    the left (column 0 replicated): ``popcount(c_l(x) XOR c_r(x - d))``. Fast kernel (bands of rows on
    the thread pool); the oracle is :func:`hamming_costs_reference`."""
    codes_left, codes_right = np.ascontiguousarray(codes_left), np.ascontiguousarray(codes_right)
    H, W, _ = codes_left.shape
    out = np.empty((H, W, int(disparities)), np.float32)
    _in_parallel(_hamming_kernel, [(codes_left, codes_right, out, y0, y1) for y0, y1 in _bands(H)])
    return out


def hamming_costs_reference(codes_left: np.ndarray, codes_right: np.ndarray, disparities: int) -> np.ndarray:
    """:func:`hamming_costs` with ``np.bitwise_count`` on one shifted slice per disparity."""
    shifted = codes_right[:, _shifted_columns(codes_right.shape[1], disparities)]  # (H, W, D, words)
    return np.bitwise_count(codes_left[:, :, None, :] ^ shifted).sum(axis=3).astype(np.float32)


@_kernel
def _census_row_sums(codes_left, codes_right, source, radius, reversed_row, counts, dest):
    """Row ``source`` of the Hamming volume, summed over ``2 radius + 1`` columns (borders replicated), into
    ``dest`` ``(W, D)`` int32. ``reversed_row`` and ``counts`` are scratch buffers."""
    H, W, words = codes_left.shape
    D = dest.shape[1]
    for w in range(words):  # reversed_row[w, (W - 1 - x) + d] = codes_right[source, max(x - d, 0), w]
        for j in range(W + D):
            reversed_row[w, j] = codes_right[source, max(W - 1 - j, 0), w]
    for x in range(W):
        base = W - 1 - x
        for d in range(D):
            counts[x, d] = 0
        for w in range(words):
            code = codes_left[source, x, w]
            for d in range(D):
                counts[x, d] += _popcount(code ^ reversed_row[w, base + d])
    sums = dest[0].copy()
    for d in range(D):
        sums[d] = 0
    for k in range(-radius, radius + 1):
        column = min(max(k, 0), W - 1)
        for d in range(D):
            sums[d] += counts[column, d]
    for x in range(W):
        enter = min(x + radius + 1, W - 1)
        leave = max(x - radius, 0)
        for d in range(D):
            dest[x, d] = sums[d]
            sums[d] += counts[enter, d] - counts[leave, d]


@_kernel
def _census_window_kernel(codes_left, codes_right, radius, factor, out, y0, y1):
    """Rows ``y0:y1`` of the census cost volume in one pass: Hamming distances summed over the window
    (borders replicated) times ``factor``, written to ``out`` (float32).

    Each row's Hamming distances are summed along the row as they are counted; a ring holds the
    row sums of the last ``2 radius + 2`` source rows and an integer accumulator slides down the
    columns. The sums are exact integers, so the result equals :func:`hamming_costs` followed by
    :func:`box_mean` (scaled), bit for bit, without writing the per-pixel volume.
    """
    H, W, words = codes_left.shape
    D = out.shape[2]
    size = 2 * radius + 2
    ring = np.empty((size, W, D), np.int32)
    held = np.full(size, -1, np.int64)  # the source row each slot of the ring holds
    reversed_row = np.empty((words, W + D), np.uint64)
    counts = np.empty((W, D), np.int32)
    acc = np.zeros((W, D), np.int32)
    for k in range(-radius, radius + 1):
        source = min(max(y0 + k, 0), H - 1)
        slot = source % size
        if held[slot] != source:
            _census_row_sums(codes_left, codes_right, source, radius, reversed_row, counts, ring[slot])
            held[slot] = source
        sums = ring[slot]
        for x in range(W):
            for d in range(D):
                acc[x, d] += sums[x, d]
    for y in range(y0, y1):
        target = out[y]
        for x in range(W):
            for d in range(D):
                target[x, d] = np.float32(acc[x, d] * factor)
        if y + 1 >= y1:
            break
        enter = min(y + radius + 1, H - 1)
        leave = max(y - radius, 0)
        if enter == leave:  # a window taller than the image: nothing changes
            continue
        slot = enter % size
        if held[slot] != enter:
            _census_row_sums(codes_left, codes_right, enter, radius, reversed_row, counts, ring[slot])
            held[slot] = enter
        entering = ring[slot]
        leaving = ring[leave % size]
        for x in range(W):
            for d in range(D):
                acc[x, d] += entering[x, d] - leaving[x, d]


def census_costs(gray_left: np.ndarray, gray_right: np.ndarray, disparities: int, window: int) -> np.ndarray:
    """The census cost volume ``(H, W, D)`` float32: the Hamming distances of the census strings over the
    ``window`` (:func:`census_transform`), averaged over the window and divided by the ``window^2 - 1``
    bits of a string, so costs lie in [0, 1].

    Equals ``box_mean(hamming_costs(c_l, c_r, D), window) / (window^2 - 1)`` bit for bit; one fused
    kernel (:func:`_census_window_kernel`, bands of rows on the thread pool) never writes the
    per-pixel Hamming volume.
    """
    window = _check_window(window, "census")
    codes_left = census_transform(gray_left, window)
    codes_right = census_transform(gray_right, window)
    H, W, _ = codes_left.shape
    out = np.empty((H, W, int(disparities)), np.float32)
    factor = 1.0 / (window * window * (window * window - 1))
    _in_parallel(_census_window_kernel, [(codes_left, codes_right, window // 2, factor, out, y0, y1)
                                          for y0, y1 in _bands(H)])
    return out


def rank_transform(gray: np.ndarray, window: int) -> np.ndarray:
    """Rank of each pixel in its ``window x window`` neighbourhood: how many neighbours are darker, ``(H, W)`` int.

    Borders replicated. Reference: Zabih and Woodfill (1994), section 2.
    """
    window = _check_window(window, "rank")
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
# Matching costs
# ----------------------------------------------------------------------------------------------------
def _shifted_columns(width: int, disparities: int) -> np.ndarray:
    """``(W, D)`` right-image column seen by left column ``x`` at disparity ``d``: ``max(x - d, 0)``."""
    return np.maximum(np.arange(width)[:, None] - np.arange(disparities)[None, :], 0)


def shifted_right(values: np.ndarray, disparities: int) -> np.ndarray:
    """The right image (or any per-pixel map) shifted by every disparity: ``(H, W) -> (H, W, D)``,
    ``out[y, x, d] = values[y, max(x - d, 0)]``."""
    return np.ascontiguousarray(values[:, _shifted_columns(values.shape[1], disparities)])


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


def cost_volume(left: Image, right: Image, *, cost: Cost = "census", window: Annotated[int, Range(1, 31)] = 5,
                max_disparity: Annotated[int, Range(1, 1024)] = 64) -> Annotated[np.ndarray, "cost_volume"]:
    """The matching cost of every left pixel at every disparity, aggregated over a square window.

    With ``a`` the left window around ``(x, y)`` and ``b`` the right window around ``(x - d, y)``
    (gray levels in [0, 1], ``n = window^2`` pixels, borders replicated), the costs are
    (Scharstein and Szeliski 2002, section 3.1; Szeliski 2022, section 12.3):

    - ``ssd``: ``(1/n) sum (a - b)^2``, sum of squared differences (``cv2.matchTemplate``'s
      TM_SQDIFF divided by n);
    - ``nssd``: normalized SSD ``sum (a - b)^2 / sqrt(sum a^2 sum b^2)`` (TM_SQDIFF_NORMED);
    - ``sad``: ``(1/n) sum |a - b|``, sum of absolute differences;
    - ``zsad``: zero-mean SAD, ``(1/n) sum |a' - b'|`` on images whose local mean (over the
      window around each pixel) is subtracted, so that a brightness offset between the cameras
      costs nothing; subtracting each window's own mean instead would not be a box filter;
    - ``ncc``: ``1 - NCC``, NCC the zero-mean normalized cross-correlation
      ``sum (a - mean a)(b - mean b) / sqrt(sum (a - mean a)^2 sum (b - mean b)^2)``
      (TM_CCOEFF_NORMED), 1 where a window is flat (its gray-level variance below
      :data:`NCC_FLAT_VARIANCE`); its window moments are float64 (:func:`_ncc_volume`);
    - ``rank``: ``(1/n) sum |r_a - r_b| / (n - 1)``, ``r`` the rank transform over the window
      (Zabih and Woodfill 1994);
    - ``census``: ``(1/n) sum hamming(c_a, c_b) / (n - 1)``, ``c`` the census bit strings over
      the window (Zabih and Woodfill 1994).

    Every sum over a window is a box filter of a per-pixel term (or product) applied to each
    disparity slice, computed with running sums in O(1) per window (:func:`box_mean`), never by
    a loop over the window's pixels; census sums its Hamming distances in one fused kernel
    (:func:`census_costs`). Color images are matched in gray.

    Args:
        cost: the matching cost.
        window: side of the square window in pixels (odd; at least 3 for rank and census).
        max_disparity: largest disparity searched (pixels); the volume holds ``max_disparity + 1``.

    Returns ``(H, W, max_disparity + 1)`` float32, ``volume[y, x, d]`` the cost of matching left
    pixel ``(x, y)`` with right pixel ``(x - d, y)`` (LESSON TASK).

    Reference: Scharstein and Szeliski (2002), sections 3.1-3.2; Zabih and Woodfill (1994).
    """
    left, right = _check_pair(left, right)
    if cost not in COSTS:
        raise InvalidControl("cost", f"must be one of {list(COSTS)}, got {cost!r}")
    window = _check_window(window, cost)
    max_disparity = _check_max_disparity(max_disparity, left.width)
    disparities = max_disparity + 1
    _entries_check(left.height, left.width, disparities)
    a, b = left.gray(), right.gray()
    if cost == "census":
        return census_costs(a, b, disparities, window)
    if cost in ("ssd", "sad", "zsad", "rank"):
        per_pixel = np.ascontiguousarray(_pixel_volume(cost, a, b, disparities, window), dtype=np.float32)
        return _box_filter_inplace(per_pixel, window, 1.0 / (window * window))
    if cost == "ncc":
        return _ncc_volume(a, b, disparities, window)
    # nssd: box means of products, computed in place so that at most three volumes live at once
    b_shifted = shifted_right(b, disparities)
    energy_b = _box_filter_inplace(np.square(b_shifted), window, 1.0 / (window * window))
    squared = np.subtract(a[:, :, None], b_shifted, out=b_shifted)
    squared = _box_filter_inplace(np.square(squared, out=squared), window, 1.0 / (window * window))
    energy_b *= box_mean(a * a, window)[:, :, None]
    np.sqrt(energy_b, out=energy_b)
    return np.divide(squared, np.maximum(energy_b, np.float32(1e-12), out=energy_b), out=squared)


#: Entries of the float64 volumes :func:`_ncc_volume` builds at once (a few disparities at a time).
NCC_CHUNK_ENTRIES = 2**22

#: A window whose gray-level variance is below this is flat: its NCC is 0 (its cost 1). One gray
#: level of an 8-bit image in one pixel of a 7 x 7 window gives a variance of about 3e-7.
NCC_FLAT_VARIANCE = 1e-10


def _box_mean64(values: np.ndarray, window: int) -> np.ndarray:
    """:func:`box_mean` in float64 of an ``(H, W)`` or ``(H, W, D)`` array (a new array)."""
    volume = np.array(values[:, :, None] if values.ndim == 2 else values, dtype=np.float64, order="C", copy=True)
    _box_filter_inplace(volume, window, 1.0 / (window * window))
    return volume[:, :, 0] if values.ndim == 2 else volume


@_kernel
def _ncc_from_moments(mean_a, var_a, mean_b, mean_bb, mean_ab, flat_variance, out, d0):
    """``out[:, :, d0 + j] = 1 - clip(NCC, -1, 1)`` from float64 window means of ``b``, ``b^2`` and ``a b``
    ``(H, W, k)`` and those of the left image; NCC = 0 where either window is flat."""
    H, W, k = mean_b.shape
    for y in range(H):
        for x in range(W):
            ma = mean_a[y, x]
            va = var_a[y, x]
            for j in range(k):
                mb = mean_b[y, x, j]
                vb = max(mean_bb[y, x, j] - mb * mb, 0.0)
                ncc = 0.0
                if va >= flat_variance and vb >= flat_variance:
                    ncc = min(max((mean_ab[y, x, j] - ma * mb) / np.sqrt(va * vb), -1.0), 1.0)
                out[y, x, d0 + j] = 1.0 - ncc


def _ncc_volume(a: np.ndarray, b: np.ndarray, disparities: int, window: int) -> np.ndarray:
    """``1 - NCC`` for every disparity, the window moments in float64, a few disparities at a time.

    ``var = mean(x^2) - mean(x)^2`` cancels badly in float32 where a window is nearly flat (a
    variance of 1e-6 next to a mean square of 0.25), so the moments are box means of float64
    slices (:func:`_box_filter_inplace`); the result is rounded to float32 once. A window with a
    variance below :data:`NCC_FLAT_VARIANCE` (in either image) gets NCC 0.
    """
    H, W = a.shape
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    mean_a = _box_mean64(a, window)
    var_a = np.maximum(_box_mean64(a * a, window) - mean_a * mean_a, 0.0)
    columns = _shifted_columns(W, disparities)
    out = np.empty((H, W, disparities), np.float32)
    chunk = max(1, min(disparities, NCC_CHUNK_ENTRIES // max(H * W, 1)))
    for d0 in range(0, disparities, chunk):
        b_shifted = b[:, columns[:, d0:d0 + chunk]]  # (H, W, k) float64, C-contiguous
        mean_bb = _box_filter_inplace(b_shifted * b_shifted, window, 1.0 / (window * window))
        mean_ab = _box_filter_inplace(np.multiply(a[:, :, None], b_shifted), window, 1.0 / (window * window))
        mean_b = _box_filter_inplace(b_shifted, window, 1.0 / (window * window))
        _ncc_from_moments(mean_a, var_a, mean_b, mean_bb, mean_ab, NCC_FLAT_VARIANCE, out, d0)
    return out


def cost_curves(left: Image, right: Image, x: int, y: int, *, costs: tuple[str, ...] = COSTS, window: int = 5,
                max_disparity: int = 64, aggregated_cost: np.ndarray | None = None) -> Curve:
    """The cost of left pixel ``(x, y)`` at every disparity, one series per cost (what the viewer plots on a click).

    Each cost is computed by :func:`cost_volume` on a crop around the pixel (rows ``y +- r``, columns
    ``x - max_disparity - r .. x + r``, ``r`` the reach of the window and of the census/rank
    transform), so a click costs milliseconds; the values equal those of the full volume.
    ``aggregated_cost`` (the state's volume, optional) adds its curve at the pixel, labelled
    "aggregated"; rank and census are left out when ``window`` is 1 (they need neighbours).
    Returns a :class:`Curve` over ``d = 0 .. max_disparity``.
    """
    left, right = _check_pair(left, right)
    if not (0 <= int(x) < left.width and 0 <= int(y) < left.height):
        raise InvalidValue("x", f"pixel ({x}, {y}) lies outside the {left.width} x {left.height} image")
    x, y = int(x), int(y)
    window = _check_window(window)
    max_disparity = _check_max_disparity(max_disparity, left.width)
    reach = 2 * (window // 2) + 1  # a transform (census, rank, local mean) then a window sum
    y0, y1 = max(0, y - reach), min(left.height, y + reach + 1)
    x0, x1 = max(0, x - max_disparity - reach), min(left.width, x + reach + 1)
    crop_l = Image(left.pixels[y0:y1, x0:x1])
    crop_r = Image(right.pixels[y0:y1, x0:x1])
    disparities = np.arange(max_disparity + 1, dtype=np.float64)
    series, labels = [], []
    for name in costs:
        if name not in COSTS:
            raise InvalidControl("costs", f"unknown cost {name!r}; costs are {list(COSTS)}")
        if window < 3 and name in ("rank", "census"):
            continue  # these compare a pixel with its neighbours: a 1 x 1 window has none
        usable = min(max_disparity, crop_l.width - 1)
        volume = cost_volume(crop_l, crop_r, cost=name, window=window, max_disparity=usable)
        curve = np.full(max_disparity + 1, volume[y - y0, x - x0, -1], dtype=np.float64)
        curve[:usable + 1] = volume[y - y0, x - x0]
        series.append(curve)
        labels.append(name)
    if aggregated_cost is not None:
        volume = np.asarray(aggregated_cost)
        if volume.ndim != 3 or volume.shape[:2] != (left.height, left.width):
            raise InvalidValue("aggregated_cost", f"expected ({left.height}, {left.width}, D), got {volume.shape}")
        curve = np.full(max_disparity + 1, np.nan)
        count = min(volume.shape[2], max_disparity + 1)
        curve[:count] = volume[y, x, :count]
        curve[count:] = curve[count - 1]
        series.append(curve)
        labels.append("aggregated")
    return Curve(disparities, np.array(series), kind="line", title=f"matching costs at ({x}, {y})",
                 xlabel="disparity (px)", ylabel="cost", labels=tuple(labels))


def volume_curve(volume: np.ndarray, x: int, y: int, *, label: str = "cost") -> Curve:
    """One pixel's column of a cost volume as a :class:`Curve` over the disparities."""
    volume = np.asarray(volume)
    if volume.ndim != 3:
        raise InvalidValue("volume", f"a cost volume is (H, W, D), got shape {volume.shape}")
    if not (0 <= int(x) < volume.shape[1] and 0 <= int(y) < volume.shape[0]):
        raise InvalidValue("x", f"pixel ({x}, {y}) lies outside the {volume.shape[1]} x {volume.shape[0]} volume")
    return Curve(np.arange(volume.shape[2], dtype=np.float64), volume[int(y), int(x)].astype(np.float64), kind="line",
                 title=f"{label} at ({x}, {y})", xlabel="disparity (px)", ylabel=label, labels=(label,))


# ----------------------------------------------------------------------------------------------------
# Semi-global matching
# ----------------------------------------------------------------------------------------------------
#: Path directions ``r = (dy, dx)``: ``L_r(p)`` follows from ``L_r(p - r)``. The first four are the 4-path set.
SGM_DIRECTIONS: tuple[tuple[int, int], ...] = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, -1), (-1, 1))


def _path_step(costs: np.ndarray, previous: np.ndarray, P1: float, P2: float) -> np.ndarray:
    """One step along a path, for a whole front of pixels at once (``(..., D)`` arrays):
    ``L(p, d) = C(p, d) + min(L(q, d), L(q, d - 1) + P1, L(q, d + 1) + P1, min_k L(q, k) + P2) - min_k L(q, k)``
    with ``q = p - r`` the previous pixel on the path."""
    best = previous.min(axis=-1, keepdims=True)
    big = np.iinfo(np.int64).max // 4
    lower = np.concatenate([np.full(previous.shape[:-1] + (1,), big), previous[..., :-1]], axis=-1)
    higher = np.concatenate([previous[..., 1:], np.full(previous.shape[:-1] + (1,), big)], axis=-1)
    return costs + np.minimum(np.minimum(previous, np.minimum(lower, higher) + P1), best + P2) - best


def sgm_reference(costs: np.ndarray, P1: int, P2: int, *, paths: int = 8) -> np.ndarray:
    """Semi-global aggregation, path by path, each path step vectorized over a whole row or column.

    ``costs`` ``(H, W, D)`` integers, ``P1 <= P2`` integers; returns ``S = sum_r L_r`` ``(H, W, D)``
    int64 over the first ``paths`` of :data:`SGM_DIRECTIONS`. A path starts (``L_r = C``) where
    ``p - r`` leaves the image. The readable oracle of the fast kernel behind
    :func:`semi_global_matching`. Reference: Hirschmüller (2008), section 3.3, equations 11-14.
    """
    C = np.asarray(costs).astype(np.int64)
    H, W, D = C.shape
    total = np.zeros_like(C)
    for dy, dx in SGM_DIRECTIONS[:paths]:
        L = np.empty_like(C)
        if dy == 0:
            columns = list(range(W)) if dx > 0 else list(range(W - 1, -1, -1))
            L[:, columns[0]] = C[:, columns[0]]
            for x in columns[1:]:
                L[:, x] = _path_step(C[:, x], L[:, x - dx], P1, P2)
        else:
            rows = list(range(H)) if dy > 0 else list(range(H - 1, -1, -1))
            L[rows[0]] = C[rows[0]]
            source = np.arange(W) - dx
            inside = (source >= 0) & (source < W)
            for y in rows[1:]:
                L[y] = C[y]  # paths entering from beyond the image border start here
                L[y, inside] = _path_step(C[y, inside], L[y - dy, source[inside]], P1, P2)
        total += L
    return total


# The two row kernels below repeat one loop (the path update of Hirschmüller's equation 13) on
# purpose: written once as an inlined helper it runs about 1.7 times slower under Numba.
@_kernel
def _sgm_row_from_previous(costs_row, previous, previous_min, current, current_min, total, shift, start, P1, P2):
    """Paths arriving from the previous row at column ``x - shift``; adds their ``L`` to ``total`` ``(W, D)``.

    ``previous``/``current`` are ``(W, D + 2)`` int16 with a large value in columns 0 and D + 1, so
    ``L(d - 1)`` and ``L(d + 1)`` need no bounds test; 16-bit integers keep 16 costs in a SIMD register.
    """
    W, D = costs_row.shape
    for x in range(W):
        source = x - shift
        best = np.int16(_SGM_LARGEST)
        if start or source < 0 or source >= W:  # the path starts here: L = C
            for d in range(D):
                value = costs_row[x, d]
                current[x, d + 1] = value
                total[x, d] += value
                best = min(best, value)
        else:
            floor = previous_min[source]
            jump = np.int16(floor + P2)
            for d in range(D):
                stay = min(previous[source, d + 1], jump)
                step = np.int16(min(previous[source, d], previous[source, d + 2]) + P1)
                value = np.int16(np.int16(costs_row[x, d] - floor) + min(stay, step))
                current[x, d + 1] = value
                total[x, d] += value
                best = min(best, value)
        current_min[x] = best


@_kernel
def _sgm_row_horizontal(costs_row, buffer, total, forward, P1, P2):
    """The path along the row (left to right when ``forward``); writes its ``L`` into ``total`` ``(W, D)``."""
    W, D = costs_row.shape
    floor = np.int16(0)
    for i in range(W):
        x = i if forward else W - 1 - i
        now = i & 1
        before = 1 - now
        best = np.int16(_SGM_LARGEST)
        if i == 0:  # the path starts here: L = C
            for d in range(D):
                value = costs_row[x, d]
                buffer[now, d + 1] = value
                total[x, d] = value
                best = min(best, value)
        else:
            jump = np.int16(floor + P2)
            for d in range(D):
                stay = min(buffer[before, d + 1], jump)
                step = np.int16(min(buffer[before, d], buffer[before, d + 2]) + P1)
                value = np.int16(np.int16(costs_row[x, d] - floor) + min(stay, step))
                buffer[now, d + 1] = value
                total[x, d] = value
                best = min(best, value)
        floor = best


@_kernel
def _sgm_sweep(volume, quantum, P1, P2, forward, diagonals, out, scale, add):
    """One sweep over the image (top-down when ``forward``, else bottom-up) that runs 2 or 4 paths at once.

    Forward: left-to-right, top-down, and the two diagonals from the row above; backward: the
    four opposite directions. Each row's costs are first rounded to integers,
    ``floor(volume * quantum + 0.5)``; then ``out[y] (+)= scale * (sum of the paths' L)``
    (float32, exact for the integer sums below 2**24 that :func:`semi_global_matching` guarantees).
    """
    H, W, D = volume.shape
    big = np.int16(_SGM_LARGEST)
    previous = np.full((3, W, D + 2), big, np.int16)
    current = np.full((3, W, D + 2), big, np.int16)
    previous_min = np.zeros((3, W), np.int16)
    current_min = np.zeros((3, W), np.int16)
    buffer = np.full((2, D + 2), big, np.int16)
    total = np.empty((W, D), np.int32)
    row = np.empty((W, D), np.int16)
    half = np.float32(0.5)
    for i in range(H):
        y = i if forward else H - 1 - i
        source = volume[y]
        for x in range(W):
            for d in range(D):
                row[x, d] = np.int16(source[x, d] * quantum + half)
        _sgm_row_horizontal(row, buffer, total, forward, P1, P2)
        for k in range(3):
            if k != 1 and not diagonals:
                continue
            _sgm_row_from_previous(row, previous[k], previous_min[k], current[k], current_min[k], total, 1 - k,
                                   i == 0, P1, P2)
        target = out[y]
        if add:
            for x in range(W):
                for d in range(D):
                    target[x, d] += np.float32(total[x, d]) * scale
        else:
            for x in range(W):
                for d in range(D):
                    target[x, d] = np.float32(total[x, d]) * scale
        previous, current = current, previous
        previous_min, current_min = current_min, previous_min
    return out


#: Path costs of the fast kernel are int16: every ``L <= C + P2`` must stay below this (and the padding).
_SGM_LARGEST = 16383


def _sgm_scale(peak: float, P2: float, paths: int) -> float:
    """A power of two ``s`` that turns costs into integers with 12 bits below the largest cost, while a path
    cost (at most ``peak + P2``) fits the kernel's 16 bits and the sum of ``paths`` paths stays below
    2**24 (exact in float32)."""
    exponent = 20
    while exponent > -40 and (peak * 2.0**exponent > 4096.0 or (peak + P2) * 2.0**exponent >= _SGM_LARGEST
                              or paths * (peak + P2) * 2.0**exponent >= 2.0**24):
        exponent -= 1
    return 2.0**exponent


def quantize_costs(volume: np.ndarray, scale: float) -> np.ndarray:
    """The integer costs SGM works on, ``floor(volume * scale + 0.5)`` as int64 (``scale`` a power of two)."""
    return np.floor(np.asarray(volume, dtype=np.float64) * scale + 0.5).astype(np.int64)


@_kernel
def _range_kernel(volume, lows, highs, y0, y1, slot):
    """Smallest and largest entry of rows ``y0:y1`` into ``lows[slot]``, ``highs[slot]`` (NaN if one is NaN)."""
    H, W, D = volume.shape
    low = np.inf
    high = -np.inf
    nan = False
    for y in range(y0, y1):
        for x in range(W):
            for d in range(D):
                value = volume[y, x, d]
                low = min(low, value)
                high = max(high, value)
                nan |= value != value
    lows[slot] = np.nan if nan else low
    highs[slot] = np.nan if nan else high


def _volume_range(volume: np.ndarray) -> tuple[float, float]:
    """``(volume.min(), volume.max())`` of a float32 ``(H, W, D)`` volume in one pass, bands of rows on the
    thread pool; NaN when the volume holds one."""
    bands = _bands(volume.shape[0])
    lows = np.empty(len(bands), np.float64)
    highs = np.empty(len(bands), np.float64)
    _in_parallel(_range_kernel, [(volume, lows, highs, y0, y1, k) for k, (y0, y1) in enumerate(bands)])
    if np.isnan(lows).any() or np.isnan(highs).any():
        return float("nan"), float("nan")
    return float(lows.min()), float(highs.max())


def _sgm_inputs(volume: np.ndarray, P1: float, P2: float, paths: int) -> tuple[np.ndarray, float, int, int]:
    """Checked non-negative costs, the quantization scale and the integer penalties."""
    volume = _check_volume(volume, "cost_volume", finite=False)
    if paths not in (4, 8):
        raise InvalidControl("paths", f"must be 4 or 8, got {paths!r}")
    P1, P2 = float(P1), float(P2)
    if P1 < 0 or P2 < P1:
        raise InvalidControl("P2", f"the penalties must satisfy 0 <= P1 <= P2, got P1 = {P1}, P2 = {P2}")
    low, high = _volume_range(volume) if volume.size else (0.0, 0.0)
    if not (np.isfinite(low) and np.isfinite(high)):
        raise InvalidValue("cost_volume", "contains NaN or infinite costs")
    if low < 0:  # SGM's result does not change when every cost moves by one constant
        volume = volume - np.float32(low)
        high -= low
    scale = _sgm_scale(high, P2, paths)
    return volume, scale, int(round(P1 * scale)), int(round(P2 * scale))


def semi_global_matching(volume: np.ndarray, *, P1: float, P2: float, paths: int = 8) -> np.ndarray:
    """Aggregate a cost volume ``(H, W, D)`` along ``paths`` (4 or 8) scanline directions; returns float32 ``S``.

    Costs and penalties are scaled by a power of two and rounded to integers (OpenCV's SGBM works
    in 16-bit integers too; :func:`quantize_costs`); the fast kernel (:func:`_sgm_sweep`, two
    sweeps of 2 or 4 paths each) then computes exactly what :func:`sgm_reference` computes on
    those integers, and ``S`` is returned in cost units (negative costs are first shifted to 0).
    """
    volume, scale, p1, p2 = _sgm_inputs(volume, P1, P2, paths)
    quantum, inverse = np.float32(scale), np.float32(1.0 / scale)
    out = np.empty(volume.shape, np.float32)
    if _workers() == 1:
        _sgm_sweep(volume, quantum, np.int16(p1), np.int16(p2), True, paths == 8, out, inverse, False)
        _sgm_sweep(volume, quantum, np.int16(p1), np.int16(p2), False, paths == 8, out, inverse, True)
        return out
    backward = np.empty(volume.shape, np.float32)  # the two sweeps run at once, each into its own volume
    _in_parallel(_sgm_sweep, [(volume, quantum, np.int16(p1), np.int16(p2), True, paths == 8, out, inverse, False),
                              (volume, quantum, np.int16(p1), np.int16(p2), False, paths == 8, backward, inverse,
                               False)])
    _in_parallel(_add_kernel, [(out, backward, y0, y1) for y0, y1 in _bands(out.shape[0])])
    return out


@_kernel
def _add_kernel(target, other, y0, y1):
    H, W, D = target.shape
    for y in range(y0, y1):
        for x in range(W):
            for d in range(D):
                target[y, x, d] += other[y, x, d]


def aggregate_costs(cost_volume: np.ndarray, *, method: Literal["sgm", "none"] = "sgm",
                    P1: Annotated[float, Range(0.0, 10.0)] = 0.05, P2: Annotated[float, Range(0.0, 100.0)] = 1.0,
                    paths: Literal[4, 8] = 8) -> Annotated[np.ndarray, "aggregated_cost"]:
    """Semi-global matching: add to every cost the cheapest way to reach it along 4 or 8 straight paths.

    Along each direction ``r`` (Hirschmüller 2008, equation 13)::

        L_r(p, d) = C(p, d) + min(L_r(p - r, d), L_r(p - r, d +- 1) + P1, min_k L_r(p - r, k) + P2)
                    - min_k L_r(p - r, k)

    so a change of one pixel in disparity between neighbours costs ``P1`` and a larger jump
    ``P2``; ``S(p, d) = sum_r L_r(p, d)`` approximates a 2D smoothness energy by 1D dynamic
    programs. ``method = "none"`` passes the window costs through (block matching).

    Args:
        method: "sgm" (semi-global matching) or "none" (block matching: the window is the only aggregation).
        P1: penalty for a disparity change of one pixel, in cost units (the normalized costs of
            :func:`cost_volume` are about 0.5 for a mismatch).
        P2: penalty for a larger disparity change (at least P1).
        paths: 4 (horizontal and vertical) or 8 (and the diagonals).

    Returns ``(H, W, D)`` float32 aggregated costs. Corresponds to the aggregation inside
    ``cv2.StereoSGBM`` (which adds Birchfield-Tomasi costs and its own post-processing).

    Reference: H. Hirschmüller, TPAMI 30(2), 2008, section 3.3.
    """
    if method == "none":
        return _check_volume(cost_volume, "cost_volume")
    return semi_global_matching(cost_volume, P1=P1, P2=P2, paths=int(paths))


# ----------------------------------------------------------------------------------------------------
# Disparity selection, left-right check, sub-pixel refinement
# ----------------------------------------------------------------------------------------------------
def winner_take_all(aggregated_cost: np.ndarray) -> Annotated[np.ndarray, "disparity_wta"]:
    """Each pixel's disparity is the one with the lowest cost: ``d(p) = argmin_d S(p, d)`` (first on ties).

    Returns ``(H, W)`` int64 (LESSON TASK). Reference: Scharstein and Szeliski (2002), section 3.3.
    """
    volume = _check_volume(aggregated_cost, "aggregated_cost", finite=False)
    winner = np.argmin(volume, axis=2)
    _check_winners(volume, winner)
    return winner


def _check_winners(volume: np.ndarray, winner: np.ndarray) -> None:
    """NaN anywhere in a pixel's costs makes it the argmin (NumPy's rule), so checking the winners' costs
    finds every NaN, and any infinite minimum, without another pass over the volume."""
    H, W, D = volume.shape
    chosen = volume.reshape(-1)[np.arange(H * W) * D + winner.reshape(-1)]
    if not np.all(np.isfinite(chosen)):
        raise InvalidValue("aggregated_cost", "contains NaN or infinite costs")


@_kernel
def _right_argmin_kernel(volume, out, y0, y1):
    H, W, D = volume.shape
    slices = np.empty((D, W), np.float32)  # one row of the volume, disparity-major
    best = np.empty(W, np.float32)
    for y in range(y0, y1):
        for x in range(W):
            for d in range(D):
                slices[d, x] = volume[y, x, d]
        for x in range(W):
            best[x] = np.inf
            out[y, x] = 0
        for d in range(D):
            for xr in range(W - d):
                value = slices[d, xr + d]
                better = value < best[xr]
                best[xr] = value if better else best[xr]
                out[y, xr] = d if better else out[y, xr]


def right_disparity(volume: np.ndarray) -> np.ndarray:
    """Winner-take-all disparity of the *right* image from the left image's volume, ``(H, W)`` int64.

    Right pixel ``(x, y)`` matches left pixel ``(x + d, y)``, so ``d_R(x, y) = argmin_d S(y, x + d, d)``
    over ``x + d < W`` (Hirschmüller 2008, section 3.4: no second matching needed). Fast kernel;
    :func:`right_disparity_reference` is the oracle.
    """
    volume = _check_volume(volume, "aggregated_cost", finite=False)
    out = np.empty(volume.shape[:2], np.int64)
    _in_parallel(_right_argmin_kernel, [(volume, out, y0, y1) for y0, y1 in _bands(volume.shape[0])])
    return out


def right_disparity_reference(volume: np.ndarray) -> np.ndarray:
    """:func:`right_disparity` with one shifted slice per disparity."""
    volume = np.asarray(volume, dtype=np.float64)
    H, W, D = volume.shape
    best = np.full((H, W), np.inf)
    out = np.zeros((H, W), np.int64)
    for d in range(D):
        costs = np.full((H, W), np.inf)
        costs[:, :W - d] = volume[:, d:, d]
        better = costs < best
        best[better] = costs[better]
        out[better] = d
    return out


def _integer_disparity(disparity: Any, name: str, shape: tuple[int, int], disparities: int) -> np.ndarray:
    values = _check_map(disparity, name, shape)
    rounded = np.rint(values)
    if np.any(rounded < 0) or np.any(rounded >= disparities):
        raise InvalidValue(name, f"winner-take-all disparities must lie in [0, {disparities - 1}] (the volume's range)")
    return rounded.astype(np.int64)


def left_right_check(aggregated_cost: np.ndarray, disparity_wta: np.ndarray, *,
                     max_difference: Annotated[int, Range(0, 16)] = 1) -> Annotated[np.ndarray, "consistent"]:
    """Keep a pixel when the right image's match points back to it: ``|d_L(x) - d_R(x - d_L(x))| <= max_difference``.

    ``d_R`` is the right image's winner-take-all disparity read from the same volume
    (:func:`right_disparity`). Occluded pixels (seen only by the left camera) and mismatches fail;
    so do pixels whose match falls left of the right image.

    Args:
        max_difference: largest disagreement (pixels) between the two disparities.

    Returns ``(H, W)`` bool, True where consistent (LESSON TASK). Corresponds to the
    ``disp12MaxDiff`` test of ``cv2.StereoSGBM``.

    Reference: Hirschmüller (2008), section 3.4 (equation 15); P. Fua, "A parallel stereo algorithm
    that produces dense depth maps and preserves image features", MVA 6 (1993).
    """
    volume = _check_volume(aggregated_cost, "aggregated_cost", finite=False)
    H, W, D = volume.shape
    left = _integer_disparity(disparity_wta, "disparity_wta", (H, W), D)
    right = right_disparity(volume)
    columns = np.arange(W)[None, :] - left
    inside = columns >= 0
    back = right[np.arange(H)[:, None], np.clip(columns, 0, W - 1)]
    return inside & (np.abs(left - back) <= int(max_difference))


@_kernel
def _costs_around_kernel(volume, centre, out, y0, y1):
    H, W, _ = volume.shape
    for y in range(y0, y1):
        for x in range(W):
            c = centre[y, x]
            for k in range(3):
                out[k, y, x] = volume[y, x, c - 1 + k]


def _costs_around(volume: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``(3, H, W)`` float64: ``C(d - 1)``, ``C(d)``, ``C(d + 1)`` of every pixel, ``d = centre`` in ``[1, D - 2]``.

    ``np.take_along_axis(volume, centre[..., None] + [-1, 0, 1], axis=2)``, in a kernel: NumPy's
    fancy indexing builds index arrays for all three axes and takes several times as long. Bands
    of rows run on the thread pool (each pixel's read is a cache miss)."""
    out = np.empty((3,) + centre.shape, np.float64)
    centre = np.ascontiguousarray(centre, dtype=np.int64)
    _in_parallel(_costs_around_kernel, [(volume, centre, out, y0, y1) for y0, y1 in _bands(centre.shape[0])])
    return out


def refine_subpixel(aggregated_cost: np.ndarray, disparity_wta: np.ndarray, *,
                    method: Literal["parabola", "none"] = "parabola") -> Annotated[np.ndarray, "disparity_subpixel"]:
    """Sub-pixel disparity from a parabola through the costs at ``d - 1``, ``d``, ``d + 1``.

    ``d* = d + (C(d - 1) - C(d + 1)) / (2 (C(d - 1) - 2 C(d) + C(d + 1)))``, the vertex, clipped to
    ``d +- 0.5``; kept at ``d`` at either end of the range or where the parabola does not open
    upwards. Returns ``(H, W)`` float64 for every pixel. Corresponds to the refinement inside
    ``cv2.StereoSGBM`` and ``cv2.StereoBM``.

    Args:
        method: "parabola" or "none" (integer disparities).

    Reference: Scharstein and Szeliski (2002), section 3.4; Hirschmüller (2008), section 3.3.
    """
    volume = _check_volume(aggregated_cost, "aggregated_cost", finite=False)
    H, W, D = volume.shape
    d = _integer_disparity(disparity_wta, "disparity_wta", (H, W), D)
    out = d.astype(np.float64)
    if method == "none" or D < 3:
        return out
    inner = (d >= 1) & (d <= D - 2)
    c0, c1, c2 = _costs_around(volume, np.clip(d, 1, D - 2))
    curvature = c0 - 2.0 * c1 + c2
    usable = inner & (curvature > 0)
    offset = np.where(usable, (c0 - c2) / (2.0 * np.where(usable, curvature, 1.0)), 0.0)
    if not (np.all(np.isfinite(c1)) and np.all(np.isfinite(offset))):
        raise InvalidValue("aggregated_cost", "contains NaN or infinite costs")
    return out + np.clip(offset, -0.5, 0.5)


# ----------------------------------------------------------------------------------------------------
# Filtering: uniqueness, peak removal, median, hole filling
# ----------------------------------------------------------------------------------------------------
@_kernel
def _best_two_kernel(volume, best, second, y0, y1):
    H, W, D = volume.shape
    slices = np.empty((D, W), np.float32)
    winner = np.empty(W, np.int64)
    for y in range(y0, y1):
        for x in range(W):
            for d in range(D):
                slices[d, x] = volume[y, x, d]
        low = best[y]
        other = second[y]
        for x in range(W):
            low[x] = np.inf
            other[x] = np.inf
            winner[x] = 0
        for d in range(D):
            for x in range(W):
                value = slices[d, x]
                better = value < low[x]
                low[x] = value if better else low[x]
                winner[x] = d if better else winner[x]
        for d in range(D):
            for x in range(W):
                value = slices[d, x]
                far = (d < winner[x] - 1) or (d > winner[x] + 1)
                other[x] = value if far and value < other[x] else other[x]


def best_two_costs(volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's lowest cost and the lowest cost at least two disparities away from the winner,
    ``(H, W)`` float32 each (``inf`` when the range has no such disparity). Fast kernel; the oracle
    is :func:`best_two_costs_reference`."""
    volume = _check_volume(volume, "aggregated_cost", finite=False)
    best = np.empty(volume.shape[:2], np.float32)
    second = np.empty(volume.shape[:2], np.float32)
    _in_parallel(_best_two_kernel, [(volume, best, second, y0, y1) for y0, y1 in _bands(volume.shape[0])])
    return best, second


def best_two_costs_reference(volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`best_two_costs` by masking the three disparities around the winner."""
    volume = np.asarray(volume, dtype=np.float64)
    winner = np.argmin(volume, axis=2)
    near = np.abs(np.arange(volume.shape[2])[None, None, :] - winner[:, :, None]) <= 1
    return volume.min(axis=2).astype(np.float32), np.where(near, np.inf, volume).min(axis=2).astype(np.float32)


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
    cv2.filterSpeckles(fixed, -16, int(max_size), int(round(max_difference * 16.0)))
    return np.where(fixed == -16, HOLE, d)


def colorize_disparity(disparity: np.ndarray, *, max_disparity: float | None = None, name: str = "disparity") -> Image:
    """A disparity map as a colour image (OpenCV's turbo colormap: far blue, near red); holes black."""
    import cv2

    d = np.asarray(disparity, dtype=np.float64)
    valid = d >= 0
    top = float(max_disparity) if max_disparity else (float(d[valid].max()) if valid.any() else 1.0)
    levels = np.clip(np.where(valid, d, 0.0) / max(top, 1e-9) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(levels, cv2.COLORMAP_TURBO)[:, :, ::-1]
    rgb = np.where(valid[:, :, None], rgb, 0).astype(np.uint8)
    return Image(rgb, name=name)


@step_result
class FilteredDisparity:
    """Result of :func:`filter_disparity`."""

    disparity: np.ndarray
    disparity_image: Image
    coverage: float = metric("fraction of pixels with a disparity")
    inconsistent: float = metric("fraction of pixels removed by the left-right check")
    ambiguous: float = metric("fraction of the remaining pixels removed by the uniqueness test")
    peaks: float = metric("fraction of pixels removed as small islands (peaks)")
    filled: float = metric("fraction of pixels filled by hole filling")


def filter_disparity(disparity_subpixel: np.ndarray, consistent: np.ndarray, aggregated_cost: np.ndarray, *,
                     median: Literal[1, 3, 5] = 3, uniqueness: Annotated[float, Range(0.0, 0.9)] = 0.05,
                     speckle_size: Annotated[int, Range(0, 100000)] = 100,
                     speckle_range: Annotated[float, Range(0.0, 16.0)] = 2.0,
                     fill: bool = False) -> FilteredDisparity:
    """Clean the disparity map: median filter, drop inconsistent, ambiguous and isolated pixels, fill holes.

    In order: a ``median x median`` median filter of the refined disparities (Hirschmüller 2008,
    section 4.1); holes (-1) where the left-right check failed or where the winner is not unique
    (its cost is not below ``1 - uniqueness`` times the best cost two or more disparities away,
    OpenCV's ``uniquenessRatio``); small islands removed (:func:`remove_peaks`, OpenCV's
    ``speckleWindowSize``/``speckleRange``); then, with ``fill``, each hole takes the background
    disparity of its row (:func:`fill_holes`).

    Args:
        median: side of the median filter (1: none).
        uniqueness: margin by which the best cost must beat the second best (0: no test).
        speckle_size: largest island (pixels) removed as a peak (0: none).
        speckle_range: largest disparity step (pixels) inside one island.
        fill: fill the holes with the background disparity of their row.

    Returns ``disparity`` ``(H, W)`` float64 with -1 in holes and ``disparity_image``.
    """
    import cv2

    volume = _check_volume(aggregated_cost, "aggregated_cost", finite=False)
    H, W, D = volume.shape
    refined = _check_map(disparity_subpixel, "disparity_subpixel", (H, W))
    mask = _check_map(consistent, "consistent", (H, W), kind="b")
    if median not in (1, 3, 5):
        raise InvalidControl("median", f"must be 1, 3 or 5, got {median!r}")
    smoothed = refined if median == 1 else cv2.medianBlur(refined.astype(np.float32), int(median)).astype(np.float64)
    keep = mask.copy()
    ambiguous = 0.0
    if uniqueness > 0:
        best, second = best_two_costs(volume)
        unique = best < (1.0 - uniqueness) * second
        ambiguous = float(np.mean(keep & ~unique)) if keep.size else 0.0
        keep &= unique
    disparity = np.where(keep, np.maximum(smoothed, 0.0), HOLE)
    before_peaks = disparity >= 0
    disparity = remove_peaks(disparity, max_size=int(speckle_size), max_difference=float(speckle_range))
    peaks = float(np.mean(before_peaks & (disparity < 0)))
    filled = 0.0
    if fill:
        holes = disparity < 0
        disparity = fill_holes(disparity)
        filled = float(np.mean(holes & (disparity >= 0)))
    return FilteredDisparity(disparity=disparity, disparity_image=colorize_disparity(disparity, max_disparity=D - 1),
                             coverage=float(np.mean(disparity >= 0)), inconsistent=float(np.mean(~mask)),
                             ambiguous=ambiguous, peaks=peaks, filled=filled)


# ----------------------------------------------------------------------------------------------------
# Rectification
# ----------------------------------------------------------------------------------------------------
def row_misalignment(left: Image, right: Image, *, max_features: int = 3000) -> tuple[float, int]:
    """How far rows of the pair disagree: ``(largest vertical offset over the image in px, matches)``.

    ORB features (``cv2.ORB_create``, away from the black borders a rectification leaves) are
    matched by Hamming distance with a cross check; the
    vertical offsets ``y_right - y_left`` of the matches are fitted (least squares, outliers
    trimmed) by ``a + b u + c v + e u v`` over normalized image coordinates, which captures a
    shift, a rotation, a scale and the keystone of verged cameras; the result is the largest
    offset that model predicts at the centre and the corners of the region the features cover
    (5 % to 95 % of them along each axis). A rectified pair gives a fraction of a pixel. Returns
    ``(-1.0, matches)`` when fewer than 50 matches fit (too little texture to tell).
    """
    import cv2

    left, right = _check_pair(left, right)
    orb = cv2.ORB_create(nfeatures=int(max_features))
    found = []
    for image in (left, right):
        gray = np.clip(image.gray() * 255.0 + 0.5, 0, 255).astype(np.uint8)
        inside = cv2.erode((gray > 0).astype(np.uint8), np.ones((31, 31), np.uint8))  # not at black borders
        found.append(orb.detectAndCompute(gray, inside))
    (points_l, descriptors_l), (points_r, descriptors_r) = found
    if descriptors_l is None or descriptors_r is None:
        return -1.0, 0
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(descriptors_l, descriptors_r)
    if len(matches) < 20:
        return -1.0, len(matches)
    xy_l = np.array([points_l[m.queryIdx].pt for m in matches])
    xy_r = np.array([points_r[m.trainIdx].pt for m in matches])
    half_w, half_h = (left.width - 1) / 2.0, (left.height - 1) / 2.0
    u, v = (xy_l[:, 0] - half_w) / left.width, (xy_l[:, 1] - half_h) / left.height
    design = np.stack([np.ones_like(u), u, v, u * v], axis=1)
    offsets = xy_r[:, 1] - xy_l[:, 1]
    keep = np.abs(offsets) < 0.1 * left.height  # a wrong match lands anywhere
    coefficients = np.zeros(4)
    for _ in range(5):
        if keep.sum() < 10:
            return -1.0, len(matches)
        coefficients = np.linalg.lstsq(design[keep], offsets[keep], rcond=None)[0]
        residual = np.abs(design @ coefficients - offsets)
        keep = residual < max(1.0, 3.0 * 1.4826 * float(np.median(residual[keep])))
    if keep.sum() < 50:
        return -1.0, len(matches)
    (u0, u1), (v0, v1) = np.quantile(u[keep], [0.05, 0.95]), np.quantile(v[keep], [0.05, 0.95])
    probes = np.array([[1.0, 0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.25 * (u0 + u1) * (v0 + v1)]]
                      + [[1.0, a, b, a * b] for a in (u0, u1) for b in (v0, v1)])  # no extrapolation
    return float(np.abs(probes @ coefficients).max()), len(matches)


@step_result
class RectifiedPair:
    """Result of :func:`rectify_pair`."""

    left: Image
    right: Image
    K: np.ndarray
    baseline: float
    disparity_offset: float
    warnings: Warnings
    focal_px: float = metric("focal length of the rectified cameras", unit="px")
    baseline_m: float = metric("distance between the camera centres", unit="m")
    left_rotation_deg: float = metric("rotation of the left camera by rectification", unit="deg")
    right_rotation_deg: float = metric("rotation of the right camera by rectification", unit="deg")
    row_error_px: float = metric("largest vertical offset between the rows of the pair, fitted to matched ORB "
                                 "features (-1: too few features)", unit="px")
    resampled: bool = metric("the images were resampled (False: the pair was rectified already)")


def rectify_pair(left_raw: Image, right_raw: Image, calibration: StereoCalibration, *,
                 max_row_error: Annotated[float, Range(0.1, 100.0)] = 1.0) -> RectifiedPair:
    """Turn both cameras so that epipolar lines become image rows, and resample the photos.

    The rectifying rotations and the common camera matrix come from Bouguet's algorithm
    (:func:`lab.geometry.rectification.stereo_rectify`, ``cv2.stereoRectify`` with zero disparity
    at infinity); every pixel of each rectified image is mapped back through the rotation and the
    lens distortion to the photo (:func:`lab.geometry.rectification.rectification_map`, as
    ``cv2.initUndistortRectifyMap``) and sampled bilinearly (``cv2.remap``, black outside).

    A pair whose calibration says it is rectified already (no rotation between the cameras, the
    right one straight to the right, no distortion, one focal length and ``cy``) passes through
    unchanged, keeping the difference of the principal points as ``disparity_offset`` (Middlebury's
    ``doffs``): then matched ORB features must share their rows (:func:`row_misalignment`), else
    the step refuses the pair.

    Args:
        max_row_error: largest vertical offset (pixels) between the rows of a pair declared
            rectified, as fitted to matched features.

    Returns ``left``, ``right`` (rectified Images), ``K`` (3, 3), ``baseline`` (metres) and
    ``disparity_offset`` (pixels, ``Z = f B / (d + disparity_offset)``).

    Reference: J.-Y. Bouguet, Camera Calibration Toolbox for Matlab; Hartley & Zisserman (2nd ed.),
    section 11.12; A. Fusiello et al., MVA 12 (2000).
    """
    import cv2

    left_raw, right_raw = _check_pair(left_raw, right_raw, names=("left_raw", "right_raw"))
    if not isinstance(calibration, StereoCalibration):
        raise InvalidValue("calibration", f"expected a StereoCalibration, got {type(calibration).__name__}")
    width, height = left_raw.width, left_raw.height
    if calibration.is_rectified():
        error, count = row_misalignment(left_raw, right_raw)
        if error > max_row_error:
            raise InvalidValue("calibration", f"the pair is not rectified: its rows disagree by up to {error:.1f} px "
                                              f"(more than {max_row_error} px, fitted to {count} matched features), "
                                              "but its calibration says it is rectified; give the full stereo "
                                              "calibration (K, distortion, R, T of both cameras) so the pair can be "
                                              "rectified")
        warnings = () if error >= 0 else ("too few features to check that the rows of the pair agree",)
        K = calibration.K_left
        return RectifiedPair(left=left_raw, right=right_raw, K=K.copy(), baseline=calibration.baseline,
                             disparity_offset=float(calibration.K_right[0, 2] - K[0, 2]), warnings=warnings,
                             focal_px=float(K[0, 0]), baseline_m=calibration.baseline, left_rotation_deg=0.0,
                             right_rotation_deg=0.0, row_error_px=error, resampled=False)
    rect = stereo_rectify(calibration.K_left, calibration.dist_left, calibration.K_right, calibration.dist_right,
                          (width, height), calibration.R, calibration.T)
    if rect.vertical:
        raise InvalidValue("calibration", "the cameras are stacked vertically (the baseline is mostly along y); "
                                          "rotate both photos by 90 degrees so that the baseline runs along the rows")
    images = []
    for image, K, dist, R_rect, P in ((left_raw, calibration.K_left, calibration.dist_left, rect.R_left, rect.P_left),
                                      (right_raw, calibration.K_right, calibration.dist_right, rect.R_right,
                                       rect.P_right)):
        mapping = rectification_map(K, dist, R_rect, P, (width, height)).astype(np.float32)
        pixels = cv2.remap(image.pixels, mapping[..., 0], mapping[..., 1], interpolation=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        images.append(Image(np.clip(pixels, 0.0, 1.0), name=f"{image.name or 'image'} (rectified)"))
    error, _ = row_misalignment(images[0], images[1])
    return RectifiedPair(left=images[0], right=images[1], K=rect.K, baseline=rect.baseline,
                         disparity_offset=rect.disparity_offset, warnings=(), focal_px=float(rect.K[0, 0]),
                         baseline_m=rect.baseline,
                         left_rotation_deg=float(rotation_angle_deg(np.eye(3), rect.R_left)),
                         right_rotation_deg=float(rotation_angle_deg(np.eye(3), rect.R_right)),
                         row_error_px=error, resampled=True)


# ----------------------------------------------------------------------------------------------------
# Depth and points
# ----------------------------------------------------------------------------------------------------
def _check_baseline(baseline: Any) -> float:
    try:
        value = float(baseline)
    except (TypeError, ValueError):
        raise InvalidValue("baseline", f"expected a number of metres, got {baseline!r}") from None
    if not np.isfinite(value) or value == 0.0:
        raise InvalidValue("baseline", f"the baseline is {value!r}: with both cameras at one place depth cannot be "
                                       "triangulated (Z = f B / d); give the distance between the cameras in metres")
    if value < 0:
        raise InvalidValue("baseline", f"must be a positive distance in metres, got {value}")
    return value


def depth_from_disparity(disparity: np.ndarray, K: np.ndarray, baseline: float, *, disparity_offset: float = 0.0,
                         disparity_std: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Depth ``Z = f B / (d + offset)`` and its uncertainty ``u_z = Z^2 u_d / (f B)`` (first-order propagation of
    a disparity uncertainty ``u_d``), ``(H, W)`` each in metres, 0 where there is no disparity or it is not positive.

    Reference: Hartley & Zisserman (2nd ed.), section 11.12; Szeliski (2022), section 12.1.
    """
    K = as_intrinsics(K)
    baseline = _check_baseline(baseline)
    d = np.asarray(disparity, dtype=np.float64) + float(disparity_offset)
    valid = (np.asarray(disparity) >= 0) & (d > 0)
    fB = K[0, 0] * baseline
    depth = np.where(valid, fB / np.where(valid, d, 1.0), 0.0)
    return depth, np.where(valid, depth * depth * float(disparity_std) / fB, 0.0)


@step_result
class Reconstruction:
    """Result of :func:`reconstruct_points`."""

    depth: np.ndarray
    depth_uncertainty: np.ndarray
    points3d: PointCloud
    cameras: Cameras
    points: int = metric("points in the cloud")
    median_depth_m: float = metric("median depth", unit="m")
    median_uncertainty_m: float = metric("median depth uncertainty", unit="m")


def reconstruct_points(disparity: np.ndarray, left: Image, K: np.ndarray, baseline: float, disparity_offset: float, *,
                       disparity_std: Annotated[float, Range(0.0, 10.0)] = 0.5,
                       stride: Annotated[int, Range(1, 16)] = 2,
                       max_depth: Annotated[float, Range(0.0, 1e6)] = 0.0) -> Reconstruction:
    """Depth, its uncertainty and a coloured point cloud from the disparity map.

    ``Z = f B / (d + disparity_offset)`` (similar triangles of the rectified pair), ``u_z = Z^2 u_d / (f B)``
    (depth gets uncertain with the square of distance), and ``X = Z K^-1 (x, y, 1)`` in the
    rectified left camera frame, coloured by the left image. ``cameras`` holds the rectified pair:
    the left camera at the origin, the right one ``baseline`` metres along x.

    Args:
        disparity_std: uncertainty ``u_d`` of a disparity (pixels).
        stride: keep every ``stride``-th pixel along rows and columns in the point cloud.
        max_depth: leave out points farther than this (metres; 0: keep all).

    Reference: Hartley & Zisserman (2nd ed.), section 11.12 (the rectified pair), section 5.2
    (propagation of uncertainty); Szeliski (2022), section 12.1.
    """
    if not isinstance(left, Image):
        raise InvalidValue("left", f"expected an Image, got {type(left).__name__}")
    d = _check_map(disparity, "disparity", (left.height, left.width))
    K = as_intrinsics(K)
    depth, uncertainty = depth_from_disparity(d, K, baseline, disparity_offset=float(disparity_offset),
                                              disparity_std=disparity_std)
    keep = depth > 0
    if max_depth > 0:
        keep &= depth <= max_depth
    grid = np.zeros_like(keep)
    grid[::int(stride), ::int(stride)] = True
    rows, columns = np.nonzero(keep & grid)
    Z = depth[rows, columns]
    y_n = (rows - K[1, 2]) / K[1, 1]
    x_n = (columns - K[0, 2] - K[0, 1] * y_n) / K[0, 0]
    xyz = np.stack([x_n * Z, y_n * Z, Z], axis=1)
    pixels = left.pixels[rows, columns]
    colors = np.repeat(pixels[:, None], 3, axis=1) if pixels.ndim == 1 else pixels
    K_right = K.copy()
    K_right[0, 2] += float(disparity_offset)
    B = _check_baseline(baseline)
    cameras = Cameras(np.stack([K, K_right]), np.stack([np.eye(3), np.eye(3)]), np.array([[0.0, 0.0, 0.0], [-B, 0, 0]]),
                      left.width, left.height)
    valid = depth > 0
    return Reconstruction(depth=depth, depth_uncertainty=uncertainty,
                          points3d=PointCloud(xyz, colors.astype(np.float64)), cameras=cameras, points=len(xyz),
                          median_depth_m=float(np.median(depth[valid])) if valid.any() else 0.0,
                          median_uncertainty_m=float(np.median(uncertainty[valid])) if valid.any() else 0.0)


# ----------------------------------------------------------------------------------------------------
# Metrics and evaluations (run after a step; truth may be empty)
# ----------------------------------------------------------------------------------------------------
#: Error thresholds (pixels) of the bad-pixel rates.
BAD_THRESHOLDS: tuple[float, ...] = (1.0, 2.0, 4.0)


def disparity_errors(disparity: np.ndarray, truth: np.ndarray, *,
                     thresholds: tuple[float, ...] = BAD_THRESHOLDS) -> dict[str, float]:
    """Bad-pixel rates, coverage and end-point error of a disparity map against the truth (fractions, pixels).

    Over the pixels with a true disparity (``truth >= 0``): ``bad{t}_all`` counts a hole (-1) or an
    error above ``t`` px as bad; ``bad{t}_pred`` is the same rate over the pixels that have a
    disparity; ``coverage`` is the fraction that has one; ``epe_px`` the mean absolute error over
    them (Scharstein and Szeliski 2002, section 5.1; Middlebury 2014's "bad 2.0" and "avgerr").
    Returns {} when the truth has no valid pixel.
    """
    d = np.asarray(disparity, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if d.shape != t.shape:
        raise InvalidValue("disparity", f"shape {d.shape} differs from the truth's {t.shape}")
    valid = t >= 0
    if not valid.any():
        return {}
    predicted = valid & (d >= 0)
    error = np.abs(d - t)
    count = int(predicted.sum())
    out: dict[str, float] = {}
    for threshold in thresholds:
        bad = error > threshold
        key = f"{threshold:g}".replace(".", "_")
        out[f"bad{key}_all"] = float(np.mean(~predicted[valid] | bad[valid]))
        out[f"bad{key}_pred"] = float(np.mean(bad[predicted])) if count else 1.0
    out["coverage"] = float(count / valid.sum())
    out["epe_px"] = float(np.mean(error[predicted])) if count else 0.0
    return out


def error_map(disparity: np.ndarray, truth: np.ndarray, *, threshold: float = 2.0) -> Image:
    """Where a disparity map is right and wrong, as an Image for the viewer.

    Green: error at most ``threshold`` px; red, brighter with the error: wrong; blue: a hole where
    the truth has a disparity; black: no truth.
    """
    d = np.asarray(disparity, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if d.shape != t.shape:
        raise InvalidValue("disparity", f"shape {d.shape} differs from the truth's {t.shape}")
    valid = t >= 0
    predicted = valid & (d >= 0)
    error = np.abs(d - t)
    rgb = np.zeros(d.shape + (3,), np.float32)
    good = predicted & (error <= threshold)
    bad = predicted & (error > threshold)
    rgb[good] = (0.1, 0.75, 0.2)
    strength = np.clip(0.5 + 0.5 * (error - threshold) / (4.0 * max(threshold, 1e-9)), 0.5, 1.0)
    rgb[bad] = np.stack([strength[bad], 0.1 * np.ones(bad.sum()), 0.1 * np.ones(bad.sum())], axis=1)
    rgb[valid & ~predicted] = (0.15, 0.35, 1.0)
    return Image(rgb, name=f"error map (bad > {threshold:g} px)")


def _truth_disparity(state: dict[str, Any], truth: dict[str, Any]) -> np.ndarray | None:
    reference = truth.get("disparity")
    left = state.get("left")
    if reference is None or not isinstance(left, Image) or np.shape(reference) != (left.height, left.width):
        return None
    return np.asarray(reference, dtype=np.float64)


def evaluate_rectification(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``epipolar_error_px``: mean (and max) vertical distance between the rectified projections of true 3D points."""
    points = truth.get("points")
    calibration = state.get("calibration")
    if points is None or not isinstance(calibration, StereoCalibration) or len(points) == 0:
        return {}
    from lab.geometry.camera import project

    left, right = state["left"], state["right"]
    rect = stereo_rectify(calibration.K_left, calibration.dist_left, calibration.K_right, calibration.dist_right,
                          (left.width, left.height), calibration.R, calibration.T)
    points = np.asarray(points, dtype=np.float64)
    in_right = points @ calibration.R.T + calibration.T
    x_l = rectify_pixels(project(points, calibration.K_left, calibration.dist_left), calibration.K_left,
                         calibration.dist_left, rect.R_left, rect.P_left)
    x_r = rectify_pixels(project(in_right, calibration.K_right, calibration.dist_right), calibration.K_right,
                         calibration.dist_right, rect.R_right, rect.P_right)
    dy = np.abs(x_l[:, 1] - x_r[:, 1])
    return {"epipolar_error_px": float(dy.mean()), "epipolar_error_max_px": float(dy.max())}


def evaluate_winner_take_all(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Bad-pixel rates of the raw winner-take-all disparities (every pixel predicted)."""
    reference = _truth_disparity(state, truth)
    return {} if reference is None else disparity_errors(state["disparity_wta"], reference)


def evaluate_left_right(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``consistent_fraction``; with truth, ``removed_wrong``: the fraction of removed pixels that were wrong
    (bad-2), and ``kept_wrong``: the fraction of kept ones that are."""
    mask = np.asarray(state["consistent"], dtype=bool)
    out = {"consistent_fraction": float(mask.mean())}
    reference = _truth_disparity(state, truth)
    if reference is not None:
        valid = reference >= 0
        wrong = np.abs(np.asarray(state["disparity_wta"], dtype=np.float64) - reference) > 2.0
        removed, kept = valid & ~mask, valid & mask
        out["removed_wrong"] = float(wrong[removed].mean()) if removed.any() else 0.0
        out["kept_wrong"] = float(wrong[kept].mean()) if kept.any() else 0.0
    return out


def evaluate_subpixel(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """End-point error and bad-pixel rates of the refined disparities (every pixel predicted)."""
    reference = _truth_disparity(state, truth)
    return {} if reference is None else disparity_errors(state["disparity_subpixel"], reference)


def evaluate_disparity(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Bad-1/2/4 over all pixels with a truth (holes count as errors) and over predicted pixels, coverage, EPE."""
    reference = _truth_disparity(state, truth)
    return {} if reference is None else disparity_errors(state["disparity"], reference)


def evaluate_depth(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With a true depth: median relative depth error and the fraction of depths within 3 ``u_z`` of the truth."""
    reference = truth.get("depth")
    depth = np.asarray(state["depth"])
    if reference is None or np.shape(reference) != depth.shape:
        return {}
    reference = np.asarray(reference, dtype=np.float64)
    both = (depth > 0) & (reference > 0)
    if not both.any():
        return {}
    error = np.abs(depth[both] - reference[both])
    return {"depth_rel_error": float(np.median(error / reference[both])),
            "within_3u": float(np.mean(error <= 3.0 * np.asarray(state["depth_uncertainty"])[both]))}


PIPELINE = Pipeline.build(
    name="stereo",
    title="Stereo disparity",
    summary="Dense depth from two views: rectify the pair, compute a cost volume (SSD, NCC, census ...), aggregate "
            "it with semi-global matching, pick disparities, check them left against right, refine them below a "
            "pixel, filter holes and peaks, and triangulate a coloured point cloud with its uncertainty.",
    steps=[rectify_pair, cost_volume, aggregate_costs, winner_take_all, left_right_check, refine_subpixel,
           filter_disparity, reconstruct_points],
    datasets=[motorcycle, synthetic, folder],
    evaluations={"rectify_pair": evaluate_rectification, "winner_take_all": evaluate_winner_take_all,
                 "left_right_check": evaluate_left_right, "refine_subpixel": evaluate_subpixel,
                 "filter_disparity": evaluate_disparity, "reconstruct_points": evaluate_depth},
)

__all__ = ["PIPELINE", "COSTS", "MAX_VOLUME_ENTRIES", "SGM_DIRECTIONS", "BAD_THRESHOLDS", "RectifiedPair",
           "FilteredDisparity", "Reconstruction", "rectify_pair", "cost_volume", "aggregate_costs", "winner_take_all",
           "left_right_check", "refine_subpixel", "filter_disparity", "reconstruct_points", "box_mean",
           "box_mean_reference", "census_transform", "census_transform_reference", "hamming_costs",
           "hamming_costs_reference", "rank_transform", "shifted_right", "semi_global_matching", "sgm_reference",
           "quantize_costs", "right_disparity", "right_disparity_reference", "best_two_costs",
           "best_two_costs_reference", "census_costs", "fill_holes", "remove_peaks", "colorize_disparity",
           "row_misalignment", "NCC_FLAT_VARIANCE", "depth_from_disparity", "disparity_errors", "error_map",
           "cost_curves", "volume_curve",
           "evaluate_rectification", "evaluate_winner_take_all", "evaluate_left_right", "evaluate_subpixel",
           "evaluate_disparity", "evaluate_depth"]
