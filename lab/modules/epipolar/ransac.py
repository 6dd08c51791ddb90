"""RANSAC for F: adaptive sampling of 8-point hypotheses, the inlier test, LO-RANSAC and the Sampson refit.

Everything that runs per batch, per new best or once per call is one compiled call
(:mod:`._kernels`), so that an easy pair (a few samples) does not pay for a hundred small NumPy calls.
Each public fast function here has a readable version in :mod:`.reference` (``x`` and
``x_reference``, same arguments, same answer): :data:`FAST` bundles the first, and
``reference.RANSAC_REFERENCE`` the second, for :func:`ransac_fundamental`.

Reference: H&Z section 4.7.1 (adaptive RANSAC, algorithm 4.5) and algorithm 11.4; M. Fischler and
R. Bolles, "Random sample consensus", CACM 24(6), 1981; O. Chum, J. Matas and J. Kittler, "Locally
optimized RANSAC", DAGM 2003; P. Torr and D. Murray, "The development and comparison of robust methods for
estimating the fundamental matrix", IJCV 24(3), 1997 (the Sampson-weighted refit).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from lab.geometry.robust import random_samples, ransac_iterations
from lab.modules.epipolar._checks import SAMPLE_SIZE, TooFewMatches
from lab.modules.epipolar._kernels import (_inlier_mask_kernel, _inliers_kernel, _local_optimization_kernel,
                                           _minimal_fundamentals_kernel, _normal_equations_kernel,
                                           _refit_kernel, _sampson_distances_kernel, _sampson_refit_kernel)

#: The error an inlier is tested on: "sampson" (:func:`~lab.modules.epipolar.sampson_distance`) or
#: "epipolar" (the larger of the two point-to-line distances, what ``cv2.FM_RANSAC`` thresholds).
Error = Literal["sampson", "epipolar"]


def minimal_fundamentals(x1: np.ndarray, x2: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """The normalized 8-point F (:func:`~lab.modules.epipolar.eight_point`) of each sample ``(B, 8)`` of
    indices into ``x1``, ``x2`` ``(M, 2)``: ``(B, 3, 3)``, unit norm; NaN for a sample of coincident
    points."""
    return _minimal_fundamentals_kernel(x1, x2, samples)


def inlier_counts(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, threshold_px: float,
                  error: Error = "sampson") -> np.ndarray:
    """How many pairs ``(M, 2)`` each of ``F`` ``(B, 3, 3)`` explains within ``threshold_px``, ``(B,)``; -1
    for an F with a non-finite entry (a degenerate sample). The error is compared squared, without forming it:
    Sampson ``r^2 <= t^2 (|F x1|^2 + |F^T x2|^2)`` (first two entries), epipolar
    ``r^2 <= t^2 min(|F x1|^2, |F^T x2|^2)``, ``r = x2^T F x1``."""
    no_masks = np.empty((0, len(x1)), dtype=bool)
    return _inliers_kernel(x1, x2, F, float(threshold_px) ** 2, error == "sampson", no_masks)


def inlier_mask(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, threshold_px: float,
                error: Error = "sampson") -> np.ndarray:
    """The pairs ``(M, 2)`` that one ``F`` ``(3, 3)`` explains within ``threshold_px``, ``(M,)`` bool (the
    test of :func:`inlier_counts`)."""
    return _inlier_mask_kernel(x1, x2, F, float(threshold_px) ** 2, error == "sampson")


def sampson_distances(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """:func:`~lab.modules.epipolar.sampson_distance` of one ``F`` ``(3, 3)`` (its readable form), as one
    loop, ``(M,)``: NaN for ``0 / 0``, ``inf`` for ``r / 0``, as NumPy divides."""
    return _sampson_distances_kernel(F, x1, x2)


def normal_equations(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                     Fn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 8-point normal equations ``A^T W A`` ``(9, 9)`` of the pairs ``mask`` selects, Hartley-normalized
    coordinates, and the normalization ``[s1, c1x, c1y, s2, c2x, c2y]`` (scale and centroid of each image).

    ``W = I`` when ``Fn`` (normalized coordinates) is all zeros; else each row is divided by its Sampson
    gradient norm under ``Fn`` (floored at 1e-12 of the largest)."""
    return _normal_equations_kernel(x1, x2, mask, Fn)


def refit(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
          Fn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normalized 8-point F of the pairs ``mask`` selects, from :func:`normal_equations` (Sampson-weighted
    under ``Fn`` unless it is all zeros): the eigenvector of the smallest eigenvalue, rank 2, ``T2^T F T1``.
    Returns ``(F, Fn, normalization)``: F unit norm in pixels, the rank-2 F of normalized coordinates and
    ``[s1, c1x, c1y, s2, c2x, c2y]``."""
    return _refit_kernel(x1, x2, mask, Fn)


def local_optimization(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, threshold_px: float,
                       error: Error = "sampson") -> tuple[np.ndarray, np.ndarray]:
    """Refit F by the 8-point algorithm on all its inliers, again while that gains inliers (at most 4 times).

    A minimal sample's F is spoiled by the noise of its 8 points and misses inliers; the refit on all
    of them is close to the best F, so its inlier ratio sets a realistic adaptive N. Returns
    ``(F, inliers)``. Reference: Chum, Matas and Kittler, "Locally optimized RANSAC", DAGM 2003.
    """
    return _local_optimization_kernel(F, x1, x2, float(threshold_px) ** 2, error == "sampson")


def sampson_refit(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                  iterations: int = 3) -> np.ndarray:
    """Iteratively reweighted 8-point on the pairs ``mask`` selects: each equation weighted by the inverse of
    its Sampson gradient norm under the previous F.

    ``x2^T F x1 / |grad|`` is the Sampson distance, so solving the 8-point system with row weights
    ``1 / |grad(F_prev)|`` minimizes the sum of squared Sampson distances with the weights frozen at the
    previous F; repeated, it settles close to the minimum of the Sampson error (the weights' own
    dependence on F is ignored, so not exactly at it: on leuven a full Levenberg-Marquardt lowers the RMS
    by another 0.1 %). Solved in normalized coordinates, where the 9 x 9 normal equations are well
    conditioned (what OpenCV's 8-point solves too). H&Z section 11.4.3; Torr and Murray, IJCV 24(3), 1997.
    """
    return _sampson_refit_kernel(F, x1, x2, mask, int(iterations))


@dataclass(frozen=True)
class RansacKernels:
    """What :func:`ransac_fundamental` calls, with the signatures of the fast functions of this module:
    :data:`FAST` (compiled), or ``reference.RANSAC_REFERENCE`` (readable NumPy; the same answers)."""

    minimal_fundamentals: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    inlier_counts: Callable[[np.ndarray, np.ndarray, np.ndarray, float, Error], np.ndarray]
    inlier_mask: Callable[[np.ndarray, np.ndarray, np.ndarray, float, Error], np.ndarray]
    local_optimization: Callable[[np.ndarray, np.ndarray, np.ndarray, float, Error],
                                 tuple[np.ndarray, np.ndarray]]
    sampson_refit: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int], np.ndarray]
    sampson_distances: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


#: The compiled functions of this module, what the step runs.
FAST = RansacKernels(minimal_fundamentals, inlier_counts, inlier_mask, local_optimization, sampson_refit,
                     sampson_distances)


@dataclass(frozen=True)
class RansacFit:
    """What :func:`ransac_fundamental` found: F, its inliers, and how the search went."""

    F: np.ndarray
    inliers: np.ndarray
    distances: np.ndarray  # the Sampson distance of every match under F, (M,)
    drawn: int  # hypotheses drawn
    best_count: int  # inliers of the best hypothesis (after its local optimization, before the refit)
    trace: np.ndarray  # (3, batches): samples drawn, best inlier count, samples needed (N), after each batch


def ransac_fundamental(x1: np.ndarray, x2: np.ndarray, *, threshold_px: float, confidence: float,
                       max_iterations: int, error: Error, refine: bool, rng: np.random.Generator,
                       kernels: RansacKernels = FAST) -> RansacFit:
    """RANSAC over 8-point samples of the pairs ``(M, 2)`` (checked, at least 8), adaptive, then the refit.

    Repeat: draw a batch of samples of 8 (8, 16, 32 ... 256 at once), solve each
    (:func:`minimal_fundamentals`), count their inliers (:func:`inlier_counts`); a new best is first
    optimized locally (:func:`local_optimization`), then the number of samples needed is recomputed from
    its inlier ratio ``w``: ``N = log(1 - confidence) / log(1 - w^8)``
    (:func:`lab.geometry.robust.ransac_iterations`), capped by ``max_iterations``; sampling stops once
    ``N`` samples are drawn. With ``refine`` the best F is refit on its inliers (:func:`sampson_refit`) and
    its inliers tested again. Raises :class:`TooFewMatches` when no F explains 8 matches.
    """
    count = len(x1)
    best_count, best_F, best_inliers = -1, None, None
    needed, drawn = int(max_iterations), 0
    trace: list[tuple[int, int, int]] = []
    batch = 8
    while drawn < needed:
        size = min(batch, needed - drawn)
        samples = random_samples(rng, count, SAMPLE_SIZE, size)
        hypotheses = kernels.minimal_fundamentals(x1, x2, samples)
        scores = kernels.inlier_counts(hypotheses, x1, x2, threshold_px, error)  # -1 for a non-finite F
        drawn += size
        winner = int(np.argmax(scores))
        if scores[winner] > best_count:  # a new best: optimize it locally, then update N
            best_F, best_inliers = kernels.local_optimization(hypotheses[winner], x1, x2, threshold_px, error)
            best_count = int(best_inliers.sum())
            needed = min(needed, max(drawn, ransac_iterations(best_count / count, SAMPLE_SIZE, confidence,
                                                              max_iterations)))
        trace.append((drawn, best_count, needed))
        batch = min(2 * batch, 256)
    if best_F is None or best_inliers is None or best_count < SAMPLE_SIZE:
        raise TooFewMatches("x1", f"no 8-point sample explains 8 or more matches within {threshold_px:g} px "
                                  f"in {drawn} tries; raise threshold_px or check the matches")
    F, inliers = best_F, best_inliers
    if refine:
        refined = kernels.sampson_refit(F, x1, x2, inliers, 3)
        again = kernels.inlier_mask(refined, x1, x2, threshold_px, error)
        if np.count_nonzero(again) >= SAMPLE_SIZE:
            F, inliers = refined, again
    return RansacFit(F, inliers, kernels.sampson_distances(F, x1, x2), drawn, best_count,
                     np.array(trace, dtype=np.float64).T)


__all__ = ["FAST", "Error", "RansacFit", "RansacKernels", "inlier_counts", "inlier_mask",
           "local_optimization", "minimal_fundamentals", "normal_equations", "ransac_fundamental", "refit",
           "sampson_distances", "sampson_refit"]
