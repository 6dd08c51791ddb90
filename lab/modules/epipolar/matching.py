"""Brute-force nearest neighbours of descriptors: float32 products, re-checked in float64 where they cannot
decide.

Reference: D. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 60(2), 2004
(section 7.1); N. Higham, Accuracy and Stability of Numerical Algorithms (2nd ed., 2002), section 3.1.
"""

from __future__ import annotations

import numpy as np

from lab.modules.epipolar._kernels import _two_nearest_scan_kernel
from lab.modules.epipolar.reference import nearest_neighbours_reference


def two_nearest_scan(dots: np.ndarray, qq: np.ndarray, tt: np.ndarray, start: int, slack: float,
                     first: np.ndarray, second: np.ndarray, unsure: np.ndarray, column_best: np.ndarray,
                     column_index: np.ndarray, column_second: np.ndarray) -> None:
    """One pass of the two-nearest-neighbour scan over a block of float32 dot products ``dots`` ``(B, T)``.

    Runs the compiled ``_two_nearest_scan_kernel`` (its docstring gives every shape and the tie and
    float32-error rules); the tests compare it with its readable reference.
    """
    _two_nearest_scan_kernel(dots, qq, tt, start, slack, first, second, unsure, column_best, column_index,
                             column_second)


def squared_distances64(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``|q_i - t_j|^2`` ``(Q, T)`` as ``|q|^2 + |t|^2 - 2 q.t`` in float64, clipped at 0 (the reference's
    formula)."""
    return np.maximum(np.sum(q * q, axis=1)[:, None] + np.sum(t * t, axis=1)[None, :] - 2.0 * q @ t.T, 0.0)


def nearest_neighbours(query: np.ndarray, train: np.ndarray, *, chunk: int = 1024) -> tuple[np.ndarray, ...]:
    """Brute-force Euclidean nearest neighbours: for each query row the two nearest train rows and, for each
    train row, its nearest query row; the float64 answer of :func:`nearest_neighbours_reference`, faster.

    Returns ``first`` ``(Q,)`` index, ``d1`` ``(Q,)`` and ``d2`` ``(Q,)`` (distances to the nearest
    and second nearest; ``inf`` when ``train`` has one row) and ``back`` ``(T,)`` the nearest query
    of each train row. Corresponds to ``cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, train, k=2)`` and
    ``.match(train, query)``.

    How: the dot products ``q.t`` come from one float32 matrix product per block of ``chunk`` queries
    (BLAS sgemm, twice the speed of float64 and half the memory), and one compiled pass over the block
    (:func:`two_nearest_scan`) finds the two nearest of every row and column from ``|q|^2 + |t|^2 - 2 q.t``.
    A float32 dot product of d-vectors is off by at most ``gamma = (d + 4) u |q| |t|`` (``u = 2^-24``: d
    roundings of the sum, one of each input; Higham, Accuracy and Stability of Numerical Algorithms, 2nd
    ed., section 3.1), so each squared distance by at most ``slack = 2 gamma + 1e-15 (|q|^2 + |t|^2)``.
    Only where two candidates lie within ``2 slack`` of each other can the order differ from the float64
    one: those rows and columns are decided again in float64. Last, ``d1`` and ``d2`` of the chosen pairs
    are computed in float64, so the ratio test compares the same numbers as the reference. The answer is
    the reference's wherever float64 itself separates the candidates (exact ties: lowest index first).
    """
    q = np.asarray(query, dtype=np.float64)
    t = np.asarray(train, dtype=np.float64)
    if len(t) < 2 or len(q) == 0:
        return nearest_neighbours_reference(q, t, chunk=chunk)
    q32, t32 = q.astype(np.float32), t.astype(np.float32)
    qq, tt = np.einsum("ij,ij->i", q, q), np.einsum("ij,ij->i", t, t)
    gamma = (q.shape[1] + 4) * 2.0 ** -24 * np.sqrt(qq.max() * tt.max())
    slack = 2.0 * gamma + 1e-15 * (qq.max() + tt.max())
    first = np.empty(len(q), dtype=np.int64)
    second = np.empty(len(q), dtype=np.int64)
    unsure = np.empty(len(q), dtype=bool)
    column_best = np.full(len(t), np.inf)
    column_second = np.full(len(t), np.inf)
    back = np.zeros(len(t), dtype=np.int64)
    for start in range(0, len(q), chunk):
        stop = min(start + chunk, len(q))
        two_nearest_scan(q32[start:stop] @ t32.T, qq[start:stop], tt, start, slack, first[start:stop],
                          second[start:stop], unsure[start:stop], column_best, back, column_second)
    rows = np.flatnonzero(unsure)  # float32 cannot order their candidates: decide them in float64
    for begin in range(0, len(rows), chunk):
        these = rows[begin:begin + chunk]
        exact = squared_distances64(q[these], t)
        first[these] = np.argmin(exact, axis=1)  # the first of equal values: lowest index
        exact[np.arange(len(these)), first[these]] = np.inf
        second[these] = np.argmin(exact, axis=1)
    columns = np.flatnonzero(column_second - column_best <= 2.0 * slack)  # the same for the back matches
    for begin in range(0, len(columns), chunk):
        these = columns[begin:begin + chunk]
        back[these] = np.argmin(squared_distances64(q, t[these]), axis=0)  # earliest query on equal values
    d1 = np.sqrt(np.maximum(qq + tt[first] - 2.0 * np.einsum("ij,ij->i", q, t[first]), 0.0))
    d2 = np.sqrt(np.maximum(qq + tt[second] - 2.0 * np.einsum("ij,ij->i", q, t[second]), 0.0))
    return first, d1, d2, back


__all__ = ["nearest_neighbours", "squared_distances64", "two_nearest_scan"]
