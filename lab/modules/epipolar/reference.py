"""The readable versions of the epipolar module's fast functions: the tests' oracles (gsplat's
``_torch_impl``).

Each ``x_reference`` computes what the public fast function ``x`` computes, with the same arguments, in
NumPy, slowly; the fast one's loop is ``_x_kernel`` in :mod:`._kernels` (:mod:`lab.core.kernels` fixes the
naming). :data:`RANSAC_REFERENCE` runs :func:`~lab.modules.epipolar.ransac.ransac_fundamental` on these
instead of the compiled functions, with the same answer. Two fast functions fall back on their reference for
inputs their kernel does not take: :func:`~lab.modules.epipolar.nearest_neighbours` (fewer than two train
rows) and :func:`~lab.modules.epipolar.degeneracy.homography_share` (a singular 4-point sample).

The inlier test has one fast path (:func:`~lab.modules.epipolar.ransac.inlier_counts` and ``inlier_mask``,
one kernel) and one reference, :func:`inlier_mask_reference`.
"""

from __future__ import annotations

import numpy as np

from lab.geometry.homogeneous import hartley_normalization
from lab.modules.epipolar._checks import SAMPLE_SIZE
from lab.modules.epipolar.distances import line_terms, sampson_distance
from lab.modules.epipolar.fundamental import design_matrix, enforce_rank2, null_vector
from lab.modules.epipolar.ransac import Error, RansacKernels
from lab.modules.epipolar.selection import SIGMA_FLOOR_PX, truncated_variance_factor


# ----------------------------------------------------------------------------------------------------
# RANSAC: the minimal solver, the inlier test, the refits
# ----------------------------------------------------------------------------------------------------
def _hartley(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hartley's normalization of ``(..., N, 2)`` (:func:`lab.geometry.homogeneous.hartley_normalization`)
    without its checks: the scale ``s`` ``(...)``, the centroid ``c`` ``(..., 2)`` and ``s (x - c)``.
    Coincident points give an infinite scale (and non-finite results, as the kernels give)."""
    centroid = np.einsum("...ni->...i", x) / x.shape[-2]  # x.mean(axis=-2), in a third of the time
    centred = x - centroid[..., None, :]
    scale = np.sqrt(2.0) / np.hypot(centred[..., 0], centred[..., 1]).mean(axis=-1)
    return scale, centroid, centred * scale[..., None, None]


def _similarity(scale: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """``T = [[s, 0, -s c0], [0, s, -s c1], [0, 0, 1]]`` ``(..., 3, 3)`` of the scale and centroid."""
    T = np.zeros((*np.shape(scale), 3, 3))
    T[..., 0, 0] = T[..., 1, 1] = scale
    T[..., :2, 2] = -scale[..., None] * centroid
    T[..., 2, 2] = 1.0
    return T


def minimal_fundamentals_reference(x1: np.ndarray, x2: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """:func:`~lab.modules.epipolar.eight_point` (normalized) of each sample ``(B, n)`` of indices,
    ``n <= 8``, batched: ``(B, 3, 3)``. The same steps (Hartley normalization, the null vector of the
    8 x 9 system by a complete QR, rank 2 by SVD, ``T2^T F T1``, unit norm) without ``eight_point``'s
    checks: a sample of coincident points has no normalization and gives NaN, as the kernel does."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        s1, c1, n1 = _hartley(x1[samples])
        s2, c2, n2 = _hartley(x2[samples])
    good = np.isfinite(s1) & np.isfinite(s2)
    out = np.full((len(samples), 3, 3), np.nan)
    if good.any():
        f = null_vector(design_matrix(n1[good], n2[good]))
        F = enforce_rank2(f.reshape((*f.shape[:-1], 3, 3)))
        F = np.swapaxes(_similarity(s2[good], c2[good]), -1, -2) @ F @ _similarity(s1[good], c1[good])
        out[good] = F / np.linalg.norm(F, axis=(-2, -1), keepdims=True)
    return out


def inlier_mask_reference(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, threshold_px: float,
                          error: Error = "sampson") -> np.ndarray:
    """Which pairs ``(M, 2)`` each F ``(..., 3, 3)`` explains within ``threshold_px``, ``(..., M)`` bool.

    The error is the Sampson distance ``|r| / sqrt(|F x1|^2 + |F^T x2|^2)`` (first two entries of each
    line, :func:`~lab.modules.epipolar.sampson_distance`) or, for "epipolar", the larger point-to-line
    distance ``|r| / min(|F x1|, |F^T x2|)``, ``r = x2^T F x1``; both compared squared, as the kernel does
    (no division, so a pair with ``r = 0`` on a line of zero normal counts as an inlier there too).
    """
    Fx1, Ftx2, residual = line_terms(F, x1, x2)
    norm2 = Fx1[..., 0, :] ** 2 + Fx1[..., 1, :] ** 2  # |(F x1)_12|^2: the line in image 2
    norm1 = Ftx2[..., 0, :] ** 2 + Ftx2[..., 1, :] ** 2  # |(F^T x2)_12|^2: the line in image 1
    scale = norm1 + norm2 if error == "sampson" else np.minimum(norm1, norm2)
    return residual * residual <= float(threshold_px) ** 2 * scale


def inlier_counts_reference(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, threshold_px: float,
                            error: Error = "sampson") -> np.ndarray:
    """How many pairs each of ``F`` ``(B, 3, 3)`` explains (:func:`inlier_mask_reference`), ``(B,)``; -1 for
    an F with a non-finite entry."""
    finite = np.all(np.isfinite(F), axis=(-2, -1))
    masks = inlier_mask_reference(np.where(finite[..., None, None], F, 0.0), x1, x2, threshold_px, error)
    return np.where(finite, np.count_nonzero(masks, axis=-1), -1)


def normal_equations_reference(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                               Fn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weighted 8-point normal equations ``A^T A`` ``(9, 9)`` of the pairs ``mask`` selects and their
    normalization ``[s1, c1x, c1y, s2, c2x, c2y]``.

    Both point sets moved by Hartley's normalization (:func:`lab.geometry.homogeneous.hartley_normalization`),
    one row of the design matrix per pair (:func:`~lab.modules.epipolar.fundamental.design_matrix`),
    divided by the pair's Sampson gradient norm under ``Fn`` (normalized coordinates; floored at 1e-12 of
    the largest) unless ``Fn`` is all zeros.
    """
    a, b = x1[mask], x2[mask]
    T1, n1 = hartley_normalization(a)
    T2, n2 = hartley_normalization(b)
    A = design_matrix(n1, n2)
    if np.any(Fn):
        Fx1, Ftx2, _ = line_terms(Fn, n1, n2)
        gradient = np.sqrt(Fx1[0] ** 2 + Fx1[1] ** 2 + Ftx2[0] ** 2 + Ftx2[1] ** 2)
        A = A / np.maximum(gradient, 1e-12 * gradient.max())[:, None]
    normalization = np.array([T1[0, 0], *a.mean(axis=0), T2[0, 0], *b.mean(axis=0)])
    return A.T @ A, normalization


def refit_reference(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                    Fn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normalized 8-point F of the pairs ``mask`` selects, Sampson-weighted under ``Fn`` unless it is all
    zeros: the eigenvector of the smallest eigenvalue of :func:`normal_equations_reference`, rank 2
    (:func:`~lab.modules.epipolar.enforce_rank2`), ``T2^T F T1``, unit norm. Returns ``(F, Fn,
    normalization)`` as :func:`~lab.modules.epipolar.ransac.refit`."""
    M, normalization = normal_equations_reference(x1, x2, mask, Fn)
    rank2 = enforce_rank2(np.linalg.eigh(M)[1][:, 0].reshape(3, 3))
    T1 = _similarity(normalization[0], normalization[1:3])
    T2 = _similarity(normalization[3], normalization[4:6])
    F = T2.T @ rank2 @ T1
    return F / np.linalg.norm(F), rank2, normalization


def sampson_refit_reference(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                            iterations: int = 3) -> np.ndarray:
    """:func:`~lab.modules.epipolar.ransac.sampson_refit`: ``iterations`` times :func:`refit_reference` of the
    pairs ``mask`` selects, each weighted by the previous F moved to normalized coordinates
    (``T2^-T F T1^-1``); F unchanged when that is all zeros."""
    T1, _ = hartley_normalization(x1[mask])
    T2, _ = hartley_normalization(x2[mask])
    Fn = np.linalg.inv(T2).T @ F @ np.linalg.inv(T1)
    if not np.any(Fn):
        return F
    for _ in range(iterations):  # the weights of each solve come from the previous F
        F, Fn, _ = refit_reference(x1, x2, mask, Fn)
    return F


def local_optimization_reference(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, threshold_px: float,
                                 error: Error = "sampson") -> tuple[np.ndarray, np.ndarray]:
    """:func:`~lab.modules.epipolar.ransac.local_optimization`: refit F on all its inliers
    (:func:`refit_reference`), again while that gains inliers, at most 4 times. Returns ``(F, inliers)``."""
    inliers = inlier_mask_reference(F, x1, x2, threshold_px, error)
    for _ in range(4):
        if inliers.sum() < SAMPLE_SIZE:
            break
        refit = refit_reference(x1, x2, inliers, np.zeros((3, 3)))[0]
        more = inlier_mask_reference(refit, x1, x2, threshold_px, error)
        if more.sum() < inliers.sum():
            break
        F, done = refit, np.array_equal(more, inliers)
        inliers = more
        if done:
            break
    return F, inliers


#: :func:`~lab.modules.epipolar.ransac.ransac_fundamental` on the readable functions: the same answer as the
#: compiled ones (``ransac.FAST``), slowly.
RANSAC_REFERENCE = RansacKernels(minimal_fundamentals_reference, inlier_counts_reference,
                                 inlier_mask_reference, local_optimization_reference, sampson_refit_reference,
                                 sampson_distance)


# ----------------------------------------------------------------------------------------------------
# The degeneracy check: the homography screen, the noise scale, the distance from a line
# ----------------------------------------------------------------------------------------------------
def homographies_4point(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Homographies ``(B, 3, 3)`` mapping each sample of 4 pairs ``(B, 4, 2)`` exactly (the 4-point DLT).

    Each pair gives the rows ``[x1, y1, 1, 0, 0, 0, -x2 x1, -x2 y1, -x2]`` and
    ``[0, 0, 0, x1, y1, 1, -y2 x1, -y2 y1, -y2]`` of ``A h = 0``; ``h`` is the null vector of the 8 x 9
    system. Points should be normalized first. ``cv2.getPerspectiveTransform`` solves the same system.
    Reference: H&Z section 4.1 (algorithm 4.1).
    """
    u1, v1 = x1[..., 0], x1[..., 1]
    u2, v2 = x2[..., 0], x2[..., 1]
    one, zero = np.ones_like(u1), np.zeros_like(u1)
    rows_u = np.stack([u1, v1, one, zero, zero, zero, -u2 * u1, -u2 * v1, -u2], axis=-1)
    rows_v = np.stack([zero, zero, zero, u1, v1, one, -v2 * u1, -v2 * v1, -v2], axis=-1)
    A = np.concatenate([rows_u, rows_v], axis=-2)
    try:  # h9 = 1: an 8 x 8 solve, ten times cheaper than the null vector (H[2, 2] = 0 is non-generic)
        h = np.linalg.solve(A[..., :8], -A[..., 8:])[..., 0]
        h = np.concatenate([h, np.ones((*h.shape[:-1], 1))], axis=-1)
    except np.linalg.LinAlgError:  # a singular sample (repeated points): the null vector, for every sample
        h = null_vector(A)
    return h.reshape((*x1.shape[:-2], 3, 3))


def homography_share_reference(x1: np.ndarray, x2: np.ndarray, picks: np.ndarray,
                               tolerance_px: float) -> float:
    """:func:`~lab.modules.epipolar.degeneracy.homography_share`: the largest fraction of the pairs ``(N, 2)``
    that the 4-point homography (:func:`homographies_4point`) of one of the samples ``picks`` ``(B, 4)`` maps
    within ``tolerance_px`` in image 2, all the homographies at once, in Hartley-normalized coordinates."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        _, _, n1 = _hartley(x1)
        s2, _, n2 = _hartley(x2)
        H = homographies_4point(n1[picks], n2[picks])  # (B, 3, 3), normalized coordinates
        mapped = (H.reshape(-1, 3) @ np.column_stack([n1, np.ones(len(n1))]).T).reshape(len(H), 3, -1)  # H x1
        du = mapped[:, 0] / mapped[:, 2] - n2[:, 0]
        dv = mapped[:, 1] / mapped[:, 2] - n2[:, 1]
        inside = du * du + dv * dv <= (tolerance_px * s2) ** 2  # (B, N): within the tolerance in image 2
    return float(np.count_nonzero(inside, axis=1).max() / len(x1))


def noise_sigma_reference(residuals: np.ndarray, *, start_px: float = 1.0, cut: float = 3.0,
                          iterations: int = 30) -> float:
    """:func:`~lab.modules.epipolar.noise_sigma`: from ``max(1.4826 median |d|, start_px)``, keep the
    residuals within ``cut`` sigma and set ``sigma^2 = mean(d^2) / E[z^2 | |z| <= cut]`` until it settles (0.1
    %) or fewer than 8 are kept; floored at ``SIGMA_FLOOR_PX``."""
    d = np.abs(residuals[np.isfinite(residuals)])
    if len(d) == 0:
        return SIGMA_FLOOR_PX
    sigma = max(1.4826 * float(np.median(d)), float(start_px), SIGMA_FLOOR_PX)
    factor = truncated_variance_factor(cut)
    for _ in range(iterations):
        kept = d[d <= cut * sigma]
        if len(kept) < SAMPLE_SIZE:
            break
        new = max(float(np.sqrt(np.mean(kept**2) / factor)), SIGMA_FLOOR_PX)
        if abs(new - sigma) <= 1e-3 * sigma:
            return new
        sigma = new
    return sigma


def distance_from_best_line_reference(x: np.ndarray, mask: np.ndarray) -> float:
    """:func:`~lab.modules.epipolar.degeneracy.distance_from_best_line`: the RMS distance (px) of ``x[mask]``
    from its best line, the smaller singular value of the centred points over ``sqrt(N)``."""
    centred = x[mask] - x[mask].mean(axis=0)
    return float(np.linalg.svd(centred, compute_uv=False)[1] / np.sqrt(np.count_nonzero(mask)))


# ----------------------------------------------------------------------------------------------------
# Matching
# ----------------------------------------------------------------------------------------------------
def nearest_neighbours_reference(query: np.ndarray, train: np.ndarray, *,
                                 chunk: int = 1024) -> tuple[np.ndarray, ...]:
    """Brute-force Euclidean nearest neighbours, all in float64: the readable oracle of
    :func:`~lab.modules.epipolar.nearest_neighbours`.

    For each query row the two nearest train rows and, for each train row, its nearest query row.
    Returns ``first`` ``(Q,)`` index, ``d1`` ``(Q,)`` and ``d2`` ``(Q,)`` (distances to the nearest
    and second nearest; ``inf`` when ``train`` has one row) and ``back`` ``(T,)`` the nearest query
    of each train row. Distances come from ``|a|^2 + |b|^2 - 2 a.b`` in float64, ``chunk`` query
    rows at a time. Corresponds to ``cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, train, k=2)`` and
    ``.match(train, query)``.
    """
    q = np.asarray(query, dtype=np.float64)
    t = np.asarray(train, dtype=np.float64)
    tt = np.sum(t * t, axis=1)
    first = np.zeros(len(q), dtype=np.int64)
    d1 = np.full(len(q), np.inf)
    d2 = np.full(len(q), np.inf)
    back_distance = np.full(len(t), np.inf)
    back = np.zeros(len(t), dtype=np.int64)
    for start in range(0, len(q), chunk):
        block = q[start:start + chunk]
        squared = np.maximum(np.sum(block * block, axis=1)[:, None] + tt[None, :] - 2.0 * block @ t.T, 0.0)
        rows = np.arange(len(block))
        if len(t) >= 2:
            two = np.argpartition(squared, 1, axis=1)[:, :2]
            pair = squared[rows[:, None], two]
            order = np.argsort(pair, axis=1)
            first[start:start + len(block)] = two[rows, order[:, 0]]
            d1[start:start + len(block)] = np.sqrt(pair[rows, order[:, 0]])
            d2[start:start + len(block)] = np.sqrt(pair[rows, order[:, 1]])
        elif len(t) == 1:
            d1[start:start + len(block)] = np.sqrt(squared[:, 0])
        column_best = np.argmin(squared, axis=0)
        column_distance = np.sqrt(squared[column_best, np.arange(len(t))])
        better = column_distance < back_distance
        back[better] = start + column_best[better]
        back_distance[better] = column_distance[better]
    return first, d1, d2, back


def two_nearest_scan_reference(dots: np.ndarray, qq: np.ndarray, tt: np.ndarray, start: int, slack: float,
                               first: np.ndarray, second: np.ndarray, unsure: np.ndarray,
                               column_best: np.ndarray, column_index: np.ndarray,
                               column_second: np.ndarray) -> None:
    """:func:`~lab.modules.epipolar.matching.two_nearest_scan` by stable sorts of the squared distances
    ``qq + tt - 2 dots`` ``(B, T)``, ``T >= 2``: each row's three smallest (the first of equal values first)
    give ``first``, ``second`` and ``unsure``; each column's two smallest among the running pair
    (``column_best``, ``column_second``, which came from earlier queries) and this block's rows update them
    and, where a row of this block is the smallest, ``column_index``."""
    squared = qq[:, None] + tt[None, :] - 2.0 * dots.astype(np.float64)
    padded = np.hstack([squared, np.full((len(squared), max(0, 3 - squared.shape[1])), np.inf)])
    order = np.argsort(padded, axis=1, kind="stable")
    best, runner, third = np.take_along_axis(padded, order[:, :3], axis=1).T
    first[:], second[:] = order[:, 0], order[:, 1]
    unsure[:] = (third - runner <= 2.0 * slack) | (runner - best <= 2.0 * slack)
    stacked = np.vstack([column_best[None], column_second[None], squared])  # earlier queries first on ties
    order = np.argsort(stacked, axis=0, kind="stable")
    smallest = np.take_along_axis(stacked, order[:2], axis=0)
    from_block = order[0] >= 2
    column_index[from_block] = start + order[0][from_block] - 2
    column_best[:], column_second[:] = smallest[0], smallest[1]


__all__ = ["RANSAC_REFERENCE", "distance_from_best_line_reference", "homographies_4point",
           "homography_share_reference", "inlier_counts_reference", "inlier_mask_reference",
           "local_optimization_reference", "minimal_fundamentals_reference", "nearest_neighbours_reference",
           "noise_sigma_reference", "normal_equations_reference", "refit_reference",
           "sampson_refit_reference", "two_nearest_scan_reference"]
