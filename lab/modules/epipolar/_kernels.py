"""The Numba kernels of the epipolar module: RANSAC's inner loops, the degeneracy screens, the matcher's scan.

Compiled with :func:`lab.core.kernels.kernel`; each is plain loops over arrays, without input checks. The
public fast function that calls ``_x_kernel`` is ``x`` (in :mod:`.ransac`, :mod:`.degeneracy`,
:mod:`.matching`) and its readable version is ``x_reference`` in :mod:`.reference`, the oracle of its test
(naming as in :mod:`lab.core.kernels`). Kernels call the compiled helpers above them, so that each compiles
once (the first call of a fresh checkout compiles them all, about 10 s; then numba's on-disk cache serves
them).
"""

from __future__ import annotations

import numpy as np

from lab.core.kernels import dispatchers_in, kernel, register_warm_up, warm_up_steps
from lab.modules.epipolar._checks import SAMPLE_SIZE


# ----------------------------------------------------------------------------------------------------
# Building blocks: one pair's epipolar terms, Hartley's normalization, T2^T F T1, rank 2, a linear solve
# ----------------------------------------------------------------------------------------------------
@kernel
def _epipolar_terms_kernel(F: np.ndarray, u1: float, v1: float, u2: float,
                           v2: float) -> tuple[float, float, float]:
    """For one pair: the algebraic residual ``x2^T F x1`` and the squared norms of the first two entries of
    ``F^T x2`` (the line in image 1) and of ``F x1`` (the line in image 2): :func:`line_terms` of one pair,
    all that the Sampson and the epipolar distances need."""
    a = F[0, 0] * u1 + F[0, 1] * v1 + F[0, 2]  # F x1: the line in image 2
    b = F[1, 0] * u1 + F[1, 1] * v1 + F[1, 2]
    c = F[2, 0] * u1 + F[2, 1] * v1 + F[2, 2]
    p = F[0, 0] * u2 + F[1, 0] * v2 + F[2, 0]  # F^T x2: the line in image 1
    q = F[0, 1] * u2 + F[1, 1] * v2 + F[2, 1]
    return u2 * a + v2 * b + c, p * p + q * q, a * a + b * b


@kernel
def _pair_normalization_kernel(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Hartley's normalization of the pairs ``mask`` selects, ``[s1, c1x, c1y, s2, c2x, c2y]``: each image's
    centroid ``c`` and the scale ``s`` that brings the mean distance from it to sqrt(2)
    (:func:`lab.geometry.homogeneous.hartley_normalization`, one pass per sum, no copies)."""
    count = 0
    c = np.zeros(4)
    for i in range(len(x1)):
        if mask[i]:
            count += 1
            c[0] += x1[i, 0]
            c[1] += x1[i, 1]
            c[2] += x2[i, 0]
            c[3] += x2[i, 1]
    c /= count
    d1 = 0.0
    d2 = 0.0
    for i in range(len(x1)):
        if mask[i]:
            d1 += np.sqrt((x1[i, 0] - c[0]) ** 2 + (x1[i, 1] - c[1]) ** 2)
            d2 += np.sqrt((x2[i, 0] - c[2]) ** 2 + (x2[i, 1] - c[3]) ** 2)
    return np.array([np.sqrt(2.0) / (d1 / count), c[0], c[1], np.sqrt(2.0) / (d2 / count), c[2], c[3]])


@kernel
def _transform_fundamental_kernel(F: np.ndarray, a1: float, b1: np.ndarray, a2: float,
                                  b2: np.ndarray) -> np.ndarray:
    """``T2^T F T1`` for ``T = [[a, 0, b0], [0, a, b1], [0, 0, 1]]`` (a similarity), written out."""
    G = np.empty((3, 3))
    for i in range(3):  # F T1
        G[i, 0], G[i, 1] = F[i, 0] * a1, F[i, 1] * a1
        G[i, 2] = F[i, 0] * b1[0] + F[i, 1] * b1[1] + F[i, 2]
    out = np.empty((3, 3))
    for j in range(3):  # T2^T (F T1)
        out[0, j], out[1, j] = a2 * G[0, j], a2 * G[1, j]
        out[2, j] = b2[0] * G[0, j] + b2[1] * G[1, j] + G[2, j]
    return out


@kernel
def _rank2_kernel(F: np.ndarray) -> np.ndarray:
    """:func:`enforce_rank2` of one ``(3, 3)``: the SVD without its smallest singular value."""
    U, singular, Vt = np.linalg.svd(F)
    rank2 = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            rank2[i, j] = U[i, 0] * singular[0] * Vt[0, j] + U[i, 1] * singular[1] * Vt[1, j]
    return rank2


@kernel
def _solve_in_place_kernel(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x`` with ``A x = b`` for a square ``A`` ``(n, n)`` by Gaussian elimination with partial pivoting
    (``np.linalg.solve``, LAPACK's ``gesv``); overwrites ``A`` and ``b``. All ``nan`` for a singular ``A``."""
    n = len(b)
    for k in range(n):
        pivot = k
        for i in range(k + 1, n):
            if abs(A[i, k]) > abs(A[pivot, k]):
                pivot = i
        if A[pivot, k] == 0.0:
            return np.full(n, np.nan)
        if pivot != k:
            for j in range(n):
                A[k, j], A[pivot, j] = A[pivot, j], A[k, j]
            b[k], b[pivot] = b[pivot], b[k]
        for i in range(k + 1, n):
            factor = A[i, k] / A[k, k]
            for j in range(k, n):
                A[i, j] -= factor * A[k, j]
            b[i] -= factor * b[k]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        total = b[i]
        for j in range(i + 1, n):
            total -= A[i, j] * x[j]
        x[i] = total / A[i, i]
    return x


# ----------------------------------------------------------------------------------------------------
# RANSAC: the minimal solver, the inlier test, the refits, the local optimization
# ----------------------------------------------------------------------------------------------------
@kernel
def _inliers_kernel(x1: np.ndarray, x2: np.ndarray, F: np.ndarray, t2: float, sampson: bool,
                    masks: np.ndarray) -> np.ndarray:
    """The inlier test, the one fast path: for each of ``F`` ``(B, 3, 3)``, how many pairs ``(M, 2)`` have an
    error within ``sqrt(t2)`` (the Sampson distance, else the larger point-to-line distance), ``(B,)``.

    Compared squared: Sampson ``r^2 <= t2 (|F x1|^2 + |F^T x2|^2)`` (first two entries), epipolar
    ``r^2 <= t2 min(|F x1|^2, |F^T x2|^2)``, ``r = x2^T F x1``. An F with a non-finite entry (a degenerate
    sample) counts -1. With ``masks`` ``(B, M)`` each F's inliers are written there too; with ``masks``
    ``(0, M)`` only counted (RANSAC's inner loop: no ``(M, B)`` temporaries, 5-10x faster than three
    matrix products on 256 hypotheses).
    """
    write = len(masks) > 0
    out = np.empty(len(F), dtype=np.int64)
    for h in range(len(F)):
        f = F[h]
        finite = np.all(np.isfinite(f))
        if not finite and not write:
            out[h] = -1
            continue
        inside = 0
        for i in range(len(x1)):
            residual, norm1, norm2 = _epipolar_terms_kernel(f, x1[i, 0], x1[i, 1], x2[i, 0], x2[i, 1])
            scale = norm1 + norm2 if sampson else min(norm1, norm2)
            inlier = residual * residual <= t2 * scale
            if write:
                masks[h, i] = inlier
            if inlier:
                inside += 1
        out[h] = inside if finite else -1
    return out


@kernel
def _inlier_mask_kernel(x1: np.ndarray, x2: np.ndarray, F: np.ndarray, t2: float,
                        sampson: bool) -> np.ndarray:
    """The inliers ``(M,)`` of one ``F`` ``(3, 3)`` by :func:`_inliers_kernel`."""
    batch = np.empty((1, 3, 3))
    batch[0] = F
    masks = np.empty((1, len(x1)), dtype=np.bool_)
    _inliers_kernel(x1, x2, batch, t2, sampson, masks)
    return masks[0]


@kernel
def _sampson_distances_kernel(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """:func:`sampson_distance` of one ``F`` ``(3, 3)`` as one loop, ``(M,)``."""
    out = np.empty(len(x1))
    for i in range(len(x1)):
        algebraic, norm1, norm2 = _epipolar_terms_kernel(F, x1[i, 0], x1[i, 1], x2[i, 0], x2[i, 1])
        gradient = np.sqrt(norm2 + norm1)
        residual = abs(algebraic)
        if gradient > 0.0:
            out[i] = residual / gradient
        else:  # as NumPy divides: r / 0 = inf, 0 / 0 and nan = nan
            out[i] = np.inf if gradient == 0.0 and residual > 0.0 else np.nan
    return out


@kernel
def _normal_equations_kernel(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                             F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 8-point normal equations ``A^T W A`` ``(9, 9)`` of the pairs ``mask`` selects, in
    Hartley-normalized coordinates, and the normalization ``[s1, c1x, c1y, s2, c2x, c2y]``.

    ``W = I`` when ``F`` (normalized coordinates) is all zeros; else each row is divided by its Sampson
    gradient norm under ``F``, ``sqrt((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2)`` (floored at
    1e-12 of the largest), as the Sampson refit needs. One pass per sum, then ``A^T A``: the loop of
    :func:`~lab.modules.epipolar.ransac.normal_equations` (its oracle: ``normal_equations_reference``).
    """
    normalization = _pair_normalization_kernel(x1, x2, mask)
    s1, s2 = normalization[0], normalization[3]
    c = np.array([normalization[1], normalization[2], normalization[4], normalization[5]])
    count = np.count_nonzero(mask)
    weighted = np.any(F != 0.0)
    gradient = np.ones(len(x1))
    if weighted:
        largest = 0.0
        for i in range(len(x1)):
            if mask[i]:
                u1, v1 = (x1[i, 0] - c[0]) * s1, (x1[i, 1] - c[1]) * s1
                u2, v2 = (x2[i, 0] - c[2]) * s2, (x2[i, 1] - c[3]) * s2
                a = F[0, 0] * u1 + F[0, 1] * v1 + F[0, 2]
                b = F[1, 0] * u1 + F[1, 1] * v1 + F[1, 2]
                p = F[0, 0] * u2 + F[1, 0] * v2 + F[2, 0]
                q = F[0, 1] * u2 + F[1, 1] * v2 + F[2, 1]
                gradient[i] = np.sqrt(a * a + b * b + p * p + q * q)
                largest = max(largest, gradient[i])
        floor = 1e-12 * largest
        for i in range(len(x1)):
            gradient[i] = max(gradient[i], floor)
    A = np.empty((count, 9))  # the weighted design matrix of the selected pairs
    r = 0
    for i in range(len(x1)):
        if mask[i]:
            u1, v1 = (x1[i, 0] - c[0]) * s1, (x1[i, 1] - c[1]) * s1
            u2, v2 = (x2[i, 0] - c[2]) * s2, (x2[i, 1] - c[3]) * s2
            w = 1.0 / gradient[i]
            A[r, 0], A[r, 1], A[r, 2] = u2 * u1 * w, u2 * v1 * w, u2 * w
            A[r, 3], A[r, 4], A[r, 5] = v2 * u1 * w, v2 * v1 * w, v2 * w
            A[r, 6], A[r, 7], A[r, 8] = u1 * w, v1 * w, w
            r += 1
    M = A.T @ A  # one BLAS product (compiled too), 5x faster than accumulating 45 sums per pair
    for j in range(9):
        for k in range(j):
            M[j, k] = M[k, j]
    return M, normalization


@kernel
def _refit_kernel(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                  Fn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normalized 8-point F of the pairs ``mask`` selects
    (Sampson-weighted under the normalized-coordinate ``Fn`` unless it is all zeros). Returns ``(F, Fn,
    normalization)``: F unit norm in pixels, the rank-2 ``Fn`` and ``[s1, c1x, c1y, s2, c2x, c2y]``."""
    M, n = _normal_equations_kernel(x1, x2, mask, Fn)
    vectors = np.linalg.eigh(M)[1]  # the eigenvector of the smallest eigenvalue: least-squares null vector
    solution = np.empty((3, 3))
    for k in range(9):
        solution[k // 3, k % 3] = vectors[k, 0]
    rank2 = _rank2_kernel(solution)
    shift1 = np.array([-n[0] * n[1], -n[0] * n[2]])
    shift2 = np.array([-n[3] * n[4], -n[3] * n[5]])
    F = _transform_fundamental_kernel(rank2, n[0], shift1, n[3], shift2)
    return F / np.sqrt(np.sum(F * F)), rank2, n


@kernel
def _minimal_fundamentals_kernel(x1: np.ndarray, x2: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """The normalized 8-point F of each sample ``(B, 8)`` (indices into ``x1``, ``x2`` ``(M, 2)``) as one
    compiled call: ``(B, 3, 3)``. The steps of :func:`eight_point` per sample: Hartley normalization, the 8 x
    9 system, its null vector as the last column of the complete QR factorization of ``A^T`` (Householder
    reflections as LAPACK's ``geqrf`` + ``orgqr``: ``Q e9 = H1 H2 ... H8 e9``), rank 2, ``T2^T F T1``, unit
    norm."""
    count, size = samples.shape
    out = np.empty((count, 3, 3))
    At = np.empty((9, size))  # A^T: a column per pair
    for h in range(count):
        c1x = c1y = c2x = c2y = 0.0
        for k in range(size):
            i = samples[h, k]
            c1x += x1[i, 0]
            c1y += x1[i, 1]
            c2x += x2[i, 0]
            c2y += x2[i, 1]
        c1x, c1y, c2x, c2y = c1x / size, c1y / size, c2x / size, c2y / size
        d1 = d2 = 0.0
        for k in range(size):
            i = samples[h, k]
            d1 += np.hypot(x1[i, 0] - c1x, x1[i, 1] - c1y)
            d2 += np.hypot(x2[i, 0] - c2x, x2[i, 1] - c2y)
        if not (d1 > 0.0 and d2 > 0.0):  # coincident points: no normalization, no F (scored -1)
            out[h] = np.nan
            continue
        s1, s2 = np.sqrt(2.0) / (d1 / size), np.sqrt(2.0) / (d2 / size)
        for k in range(size):
            i = samples[h, k]
            u1, v1 = (x1[i, 0] - c1x) * s1, (x1[i, 1] - c1y) * s1
            u2, v2 = (x2[i, 0] - c2x) * s2, (x2[i, 1] - c2y) * s2
            At[0, k], At[1, k], At[2, k] = u2 * u1, u2 * v1, u2
            At[3, k], At[4, k], At[5, k] = v2 * u1, v2 * v1, v2
            At[6, k], At[7, k], At[8, k] = u1, v1, 1.0
        taus = np.zeros(size)
        for k in range(size):  # Householder QR of A^T (9 x size), reflectors stored below the diagonal
            norm = 0.0
            for r in range(k, 9):
                norm += At[r, k] * At[r, k]
            norm = np.sqrt(norm)
            if norm == 0.0:
                continue
            alpha = At[k, k]
            beta = -norm if alpha >= 0.0 else norm
            taus[k] = (beta - alpha) / beta
            scale = 1.0 / (alpha - beta)
            for r in range(k + 1, 9):
                At[r, k] *= scale
            At[k, k] = beta
            for j in range(k + 1, size):  # apply H_k = I - tau w w^T (w = [1, At[k+1:, k]]) to the rest
                dot = At[k, j]
                for r in range(k + 1, 9):
                    dot += At[r, k] * At[r, j]
                dot *= taus[k]
                At[k, j] -= dot
                for r in range(k + 1, 9):
                    At[r, j] -= dot * At[r, k]
        f = np.zeros(9)  # Q e9, the null vector
        f[8] = 1.0
        for k in range(size - 1, -1, -1):
            dot = f[k]
            for r in range(k + 1, 9):
                dot += At[r, k] * f[r]
            dot *= taus[k]
            f[k] -= dot
            for r in range(k + 1, 9):
                f[r] -= dot * At[r, k]
        Fn = np.empty((3, 3))
        for k in range(9):
            Fn[k // 3, k % 3] = f[k]
        F = _transform_fundamental_kernel(_rank2_kernel(Fn), s1, np.array([-s1 * c1x, -s1 * c1y]), s2,
                                          np.array([-s2 * c2x, -s2 * c2y]))
        out[h] = F / np.sqrt(np.sum(F * F))
    return out


@kernel
def _local_optimization_kernel(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, t2: float,
                               sampson: bool) -> tuple[np.ndarray, np.ndarray]:
    """LO-RANSAC's local optimization as one compiled call (``t2``: squared threshold; ``sampson``: the
    error): refit on all the inliers while that gains inliers, at most 4 times. Returns ``(F, inliers)``."""
    inliers = _inlier_mask_kernel(x1, x2, F, t2, sampson)
    unweighted = np.zeros((3, 3))
    for _ in range(4):
        count = np.sum(inliers)
        if count < SAMPLE_SIZE:
            break
        refit = _refit_kernel(x1, x2, inliers, unweighted)[0]
        more = _inlier_mask_kernel(x1, x2, refit, t2, sampson)
        if np.sum(more) < count:
            break
        done = np.all(more == inliers)
        F, inliers = refit, more
        if done:
            break
    return F, inliers


@kernel
def _sampson_refit_kernel(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                          iterations: int) -> np.ndarray:
    """The iteratively Sampson-weighted 8-point refit of the pairs ``mask`` selects (no copies), one call."""
    n = _pair_normalization_kernel(x1, x2, mask)
    # T2^-T F T1^-1: F in normalized coordinates
    Fn = _transform_fundamental_kernel(F, 1.0 / n[0], n[1:3].copy(), 1.0 / n[3], n[4:6].copy())
    if not np.any(Fn != 0.0):
        return F
    for _ in range(iterations):  # the weights of each solve come from the previous F
        F, Fn, _ = _refit_kernel(x1, x2, mask, Fn)
    return F


# ----------------------------------------------------------------------------------------------------
# The degeneracy check's screens and noise scale; the matcher's scan
# ----------------------------------------------------------------------------------------------------
@kernel
def _distance_from_best_line_kernel(x: np.ndarray, mask: np.ndarray) -> float:
    """RMS distance (px) of the points ``x[mask]`` ``(N, 2)`` from their best line, without copying them:
    the square root of the smaller eigenvalue of their 2 x 2 covariance, in closed form. The same number as
    :func:`check_collinear`'s ``singular[1] / sqrt(N)``, to ~1e-16 of the largest over the smallest spread
    (plenty to screen against a threshold of 0.01 px or more)."""
    count = 0
    cx = 0.0
    cy = 0.0
    for i in range(len(x)):
        if mask[i]:
            count += 1
            cx += x[i, 0]
            cy += x[i, 1]
    cx /= count
    cy /= count
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    for i in range(len(x)):
        if mask[i]:
            dx, dy = x[i, 0] - cx, x[i, 1] - cy
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
    half_trace = 0.5 * (sxx + syy) / count
    radius = np.sqrt((0.5 * (sxx - syy) / count) ** 2 + (sxy / count) ** 2)
    return np.sqrt(max(half_trace - radius, 0.0))


@kernel
def _homography_share_kernel(x1: np.ndarray, x2: np.ndarray, picks: np.ndarray, tolerance_px: float) -> float:
    """The largest share of the pairs that one 4-point homography of the samples ``picks`` ``(B, 4)`` maps
    within ``tolerance_px``.

    The steps of ``homography_share_reference``: Hartley-normalize both point sets, the 4-point homography of
    each sample with ``h9 = 1`` (an 8 x 8 solve, Gaussian elimination with partial pivoting as LAPACK's
    ``gesv``, written out because numba's ``np.linalg.solve`` takes seconds to compile), the largest count of
    pairs mapped within the tolerance in image 2. Returns -1 for a singular sample (repeated points): the
    caller then falls back on the reference and its null vectors.
    """
    count = len(x1)
    normalization = _pair_normalization_kernel(x1, x2, np.ones(count, dtype=np.bool_))
    s1, s2 = normalization[0], normalization[3]
    centre = np.array([normalization[1], normalization[2], normalization[4], normalization[5]])
    n1 = np.empty((count, 2))
    n2 = np.empty((count, 2))
    for i in range(count):
        n1[i, 0], n1[i, 1] = (x1[i, 0] - centre[0]) * s1, (x1[i, 1] - centre[1]) * s1
        n2[i, 0], n2[i, 1] = (x2[i, 0] - centre[2]) * s2, (x2[i, 1] - centre[3]) * s2
    limit = (tolerance_px * s2) ** 2
    best = 0
    A = np.empty((8, 8))
    rhs = np.empty(8)
    for b in range(len(picks)):
        for k in range(4):
            u1, v1 = n1[picks[b, k], 0], n1[picks[b, k], 1]
            u2, v2 = n2[picks[b, k], 0], n2[picks[b, k], 1]
            A[k, 0], A[k, 1], A[k, 2], A[k, 3], A[k, 4], A[k, 5] = u1, v1, 1.0, 0.0, 0.0, 0.0
            A[k, 6], A[k, 7], rhs[k] = -u2 * u1, -u2 * v1, u2
            A[k + 4, 0], A[k + 4, 1], A[k + 4, 2], A[k + 4, 3], A[k + 4, 4] = 0.0, 0.0, 0.0, u1, v1
            A[k + 4, 5], A[k + 4, 6], A[k + 4, 7], rhs[k + 4] = 1.0, -v2 * u1, -v2 * v1, v2
        h = _solve_in_place_kernel(A, rhs)
        if h[0] != h[0]:  # nan: singular
            return -1.0
        inside = 0
        for i in range(count):
            u, v = n1[i, 0], n1[i, 1]
            w = h[6] * u + h[7] * v + 1.0
            du = (h[0] * u + h[1] * v + h[2]) / w - n2[i, 0]
            dv = (h[3] * u + h[4] * v + h[5]) / w - n2[i, 1]
            if du * du + dv * dv <= limit:
                inside += 1
        best = max(best, inside)
    return best / count


@kernel
def _noise_sigma_kernel(d: np.ndarray, sigma: float, cut: float, factor: float, iterations: int,
                        floor: float) -> float:
    """The loop of :func:`noise_sigma` compiled: ``d`` the finite absolute residuals, ``sigma`` the start
    (``max(1.4826 median, start_px, floor)``), ``factor`` :func:`truncated_variance_factor` of ``cut``."""
    for _ in range(iterations):
        total = 0.0
        kept = 0
        for value in d:
            if value <= cut * sigma:
                total += value * value
                kept += 1
        if kept < SAMPLE_SIZE:
            break
        new = max(np.sqrt(total / kept / factor), floor)
        if abs(new - sigma) <= 1e-3 * sigma:
            return new
        sigma = new
    return sigma


@kernel
def _two_nearest_scan_kernel(dots: np.ndarray, qq: np.ndarray, tt: np.ndarray, start: int, slack: float,
                             first: np.ndarray, second: np.ndarray, unsure: np.ndarray,
                             column_best: np.ndarray, column_index: np.ndarray,
                             column_second: np.ndarray) -> None:
    """One pass over a block of float32 dot products ``dots`` ``(B, T)`` (query rows ``start ...``): the two
    nearest train rows of each query and the two nearest queries of each train row, by the squared distances
    ``qq + tt - 2 dots`` (``qq`` ``(B,)``, ``tt`` ``(T,)`` float64).

    Writes ``first``, ``second`` ``(B,)`` (train indices, lowest index first on equal values) and ``unsure``
    ``(B,)``: True when the third nearest train row comes within ``2 slack`` of the second or the two nearest
    are within ``2 slack`` of each other (``slack`` bounds the error of a float32 distance, so only then can
    the float64 order differ). Updates ``column_best``, ``column_index``, ``column_second`` ``(T,)`` (the
    smallest and second smallest squared distance of each train row over the queries seen so far, the
    index of the smallest, earliest query on equal values).
    """
    rows, columns = dots.shape
    for i in range(rows):
        best = np.inf
        runner = np.inf
        third = np.inf
        j1 = 0
        j2 = 0
        for j in range(columns):
            s = qq[i] + tt[j] - 2.0 * dots[i, j]
            if s < third:
                if s < best:
                    third, runner, j2 = runner, best, j1
                    best, j1 = s, j
                elif s < runner:
                    third, runner, j2 = runner, s, j
                else:
                    third = s
            if s < column_second[j]:
                if s < column_best[j]:
                    column_second[j] = column_best[j]
                    column_best[j] = s
                    column_index[j] = start + i
                else:
                    column_second[j] = s
        first[i], second[i] = j1, j2
        unsure[i] = third - runner <= 2.0 * slack or runner - best <= 2.0 * slack


# ----------------------------------------------------------------------------------------------------
# Warm-up (lab.core.kernels): the steps that call these kernels, run once on a small rendered pair
# ----------------------------------------------------------------------------------------------------
def _warm_up() -> None:
    """Match, the 8-point fit and RANSAC (with its degeneracy screens) on a 320 x 240 rendered pair."""
    from lab.modules.epipolar import PIPELINE

    warm_up_steps(PIPELINE, "rendered", {"width": 320, "height": 240}, "estimate_fundamental_ransac")


register_warm_up("epipolar", ("match_features", "estimate_fundamental_8point", "estimate_fundamental_ransac"),
                 dispatchers_in(globals()), _warm_up)
