"""The readable versions of the stereo module's fast kernels: the tests' oracles (gsplat's ``_torch_impl``).

Each ``x_reference`` computes what the public fast function ``x`` computes, in NumPy and plain
Python, slowly; the fast one's loop is ``_x_kernel`` in :mod:`._kernels` (:mod:`lab.core.kernels`
fixes the naming). ``sgm_reference`` is the oracle of :func:`~lab.modules.stereo.semi_global_matching`
on the integer costs it works on (:func:`~lab.modules.stereo.quantize_costs`).
"""

from __future__ import annotations

import numpy as np

from lab.modules.stereo.costs import census_words, shifted_columns
from lab.modules.stereo.realtime import INVALID, gray_levels
from lab.modules.stereo.sgm import SGM_DIRECTIONS


def box_mean_reference(values: np.ndarray, window: int) -> np.ndarray:
    """:func:`box_mean` by a summed-area table (Crow 1984): pad by replication, cumulative sums along
    rows and columns, and each window's sum from four table entries,
    ``S(y2, x2) - S(y1, x2) - S(y2, x1) + S(y1, x1)``."""
    array = np.asarray(values, dtype=np.float64)
    r = window // 2
    pad = [(r, r), (r, r)] + [(0, 0)] * (array.ndim - 2)
    padded = np.pad(array, pad, mode="edge")
    table = np.zeros((padded.shape[0] + 1, padded.shape[1] + 1, *padded.shape[2:]))
    table[1:, 1:] = padded.cumsum(axis=0).cumsum(axis=1)
    H, W = array.shape[:2]
    sums = table[window:window + H, window:window + W] - table[:H, window:window + W] \
        - table[window:window + H, :W] + table[:H, :W]
    return (sums / (window * window)).astype(np.float32)


def census_transform_reference(gray: np.ndarray, window: int) -> np.ndarray:
    """:func:`census_transform` with one shifted comparison of the whole image per neighbour."""
    r = window // 2
    H, W = gray.shape
    padded = np.pad(np.asarray(gray, dtype=np.float32), r, mode="edge")
    out = np.zeros((H, W, census_words(window)), np.uint64)
    bit = 0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx == 0:
                continue
            darker = padded[r + dy:r + dy + H, r + dx:r + dx + W] < gray
            out[:, :, bit // 64] |= darker.astype(np.uint64) << np.uint64(bit % 64)
            bit += 1
    return out


def hamming_costs_reference(codes_left: np.ndarray, codes_right: np.ndarray, disparities: int) -> np.ndarray:
    """:func:`hamming_costs` with ``np.bitwise_count`` on one shifted slice per disparity."""
    shifted = codes_right[:, shifted_columns(codes_right.shape[1], disparities)]  # (H, W, D, words)
    return np.bitwise_count(codes_left[:, :, None, :] ^ shifted).sum(axis=3).astype(np.float32)


def _path_step(costs: np.ndarray, previous: np.ndarray, P1: float, P2: float) -> np.ndarray:
    """One step along a path, for a whole front of pixels at once (``(..., D)`` arrays):
    ``L(p, d) = C(p, d) + min(L(q, d), L(q, d - 1) + P1, L(q, d + 1) + P1, min_k L(q, k) + P2)
    - min_k L(q, k)``
    with ``q = p - r`` the previous pixel on the path."""
    best = previous.min(axis=-1, keepdims=True)
    big = np.iinfo(np.int64).max // 4
    lower = np.concatenate([np.full((*previous.shape[:-1], 1), big), previous[..., :-1]], axis=-1)
    higher = np.concatenate([previous[..., 1:], np.full((*previous.shape[:-1], 1), big)], axis=-1)
    return costs + np.minimum(np.minimum(previous, np.minimum(lower, higher) + P1), best + P2) - best


def sgm_reference(costs: np.ndarray, P1: int, P2: int, *, paths: int = 8) -> np.ndarray:
    """Semi-global aggregation, path by path, each path step vectorized over a whole row or column.

    ``costs`` ``(H, W, D)`` integers, ``P1 <= P2`` integers; returns ``S = sum_r L_r`` ``(H, W, D)``
    int64 over the first ``paths`` of :data:`SGM_DIRECTIONS`. A path starts (``L_r = C``) where
    ``p - r`` leaves the image. The readable oracle of the fast kernel behind
    :func:`semi_global_matching`. Reference: Hirschmüller (2008), section 3.3, equations 11-14.
    """
    C = np.asarray(costs).astype(np.int64)
    H, W, _D = C.shape
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


def best_two_costs_reference(volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`best_two_costs` by masking the three disparities around the winner."""
    volume = np.asarray(volume, dtype=np.float64)
    winner = np.argmin(volume, axis=2)
    near = np.abs(np.arange(volume.shape[2])[None, None, :] - winner[:, :, None]) <= 1
    second = np.where(near, np.inf, volume).min(axis=2)
    return volume.min(axis=2).astype(np.float32), second.astype(np.float32)


def block_match_realtime_reference(left: np.ndarray, right: np.ndarray, *, max_disparity: int = 31,
                                   block: int = 9) -> np.ndarray:
    """:func:`block_match_realtime` with one whole-image slice per disparity: ``|L(x) - R(x - d)|`` on the
    8-bit levels, its window means by the summed-area table of :func:`box_mean_reference` (float32 means
    of integer sums: distinct sums stay distinct and in order, so the argmin is the integer SAD's),
    ``np.argmin`` over the disparities, and -1 where a window leaves the image."""
    a = gray_levels(left, "left").astype(np.float64)
    b = gray_levels(right, "right").astype(np.float64)
    H, W = a.shape
    r = block // 2
    costs = np.empty((H, W, max_disparity + 1), np.float64)
    for d in range(max_disparity + 1):
        difference = np.abs(a - b[:, np.maximum(np.arange(W) - d, 0)])
        costs[:, :, d] = box_mean_reference(difference, block)
    disparity = np.argmin(costs, axis=2).astype(np.int64)
    valid = np.zeros((H, W), bool)
    valid[r:H - r, r + max_disparity:W - r] = True
    return np.where(valid, disparity, INVALID)
