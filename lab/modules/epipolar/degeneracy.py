"""Degenerate input: points on one line, on one plane, or seen from one centre, for which F is not determined.

Reference: H&Z section 11.9 (degeneracies); P. Torr, CVPR 1997 and Phil. Trans. R. Soc. A 356, 1998 (GRIC);
O. Chum, T. Werner and J. Matas, "Two-view geometry estimation unaffected by a dominant plane", CVPR 2005.
"""

from __future__ import annotations

import functools

import numpy as np

from lab.geometry.homogeneous import hartley_normalization, to_homogeneous
from lab.geometry.robust import random_samples
from lab.modules.epipolar._checks import SAMPLE_SIZE, CollinearPoints, CoplanarPoints, ZeroBaseline
from lab.modules.epipolar._kernels import _distance_from_best_line_kernel, _homography_share_kernel
from lab.modules.epipolar.distances import sampson_distance
from lab.modules.epipolar.fundamental import design_matrix
from lab.modules.epipolar.reference import homography_share_reference
from lab.modules.epipolar.selection import (GRIC_F, GRIC_H, GRIC_LAMBDA3, GRIC_R, gric,
                                            homography_sampson_distance, noise_sigma,
                                            truncated_variance_factor)

#: How much looser than the inlier threshold the fast homography screen is, and the share of the F-consistent
#: pairs above which the full model selection (GRIC) runs: a raw 4-point homography of noisy points maps a
#: plane's points less tightly than a refined one. Measured with threshold 1 px, within 2 x 2 px: one plane or
#: one centre with 0.5 px noise 89-100 %, with 1 px noise 71-96 %; general scenes 4-16 %, the rendered room
#: 26 %, leuven 47 %. The tolerance is also at least ``SCREEN_SIGMAS`` times the measured noise, so that a
#: plane with more noise than the threshold (sigma = 2 px at 1 px) still reaches GRIC.
SCREEN_TOLERANCE = 2.0
SCREEN_SHARE = 0.6
SCREEN_SIGMAS = 6.0

#: Largest mean increase of the squared normalized Sampson error (``e^2 / sigma^2`` per pair) when a
#: homography's eigenvalues are forced to modulus 1, for it to count as a rotation's: the pairs move by less
#: than sigma / 2 RMS. Measured (300 pairs, 0.5 and 2 px noise): one centre 0.00-0.16, one plane 0.40-2.4
#: (planes whose own homography is within 1 % of a rotation's included).
ROTATION_EXTRA_COST = 0.25


def check_collinear(x: np.ndarray, name: str, tolerance: float) -> None:
    """Raise :class:`CollinearPoints` when the RMS distance of ``x`` from its best line is <= tolerance."""
    centred = x - x.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    rms_off_line = singular[1] / np.sqrt(len(x))
    if rms_off_line <= tolerance:
        spread = singular[0] / np.sqrt(len(x))
        raise CollinearPoints(name, f"all {len(x)} points lie on one line (RMS distance from it "
                                    f"{rms_off_line:.3g} px, spread along it {spread:.3g} px): the epipolar "
                                    "geometry is not determined; match points spread over the image")


def check_determined(x1: np.ndarray, x2: np.ndarray) -> None:
    """Raise unless the pairs ``(M, 2)`` give the 8-point algorithm 8 independent equations (exact input):
    :class:`CollinearPoints` when the points of an image lie on one line, :class:`ZeroBaseline` when
    fewer than 8 are independent and one homography that is a rotation maps image 1 onto image 2, else
    :class:`CoplanarPoints`. The rank is read from the singular values of the Hartley-normalized design
    matrix (:func:`~lab.modules.epipolar.fundamental.design_matrix`), the 8th at most 1e-9 of the first.
    """
    for name, x in (("x1", x1), ("x2", x2)):
        check_collinear(x, name, 1e-9 * (1.0 + np.abs(x).max()))
    singular = np.linalg.svd(design_matrix(hartley_normalization(x1)[1], hartley_normalization(x2)[1]),
                             compute_uv=False)
    if singular[7] <= 1e-9 * singular[0]:
        if is_rotation_homography(x1, x2):
            raise ZeroBaseline("x1", "the matches give fewer than 8 independent equations, so F is not "
                                     "unique, and one homography that is (close to) a rotation maps image 1 "
                                     "onto image 2: the two cameras share their centre (zero baseline); "
                                     "move the camera between the photos")
        raise CoplanarPoints("x1", "the matches give fewer than 8 independent equations, so F is not "
                                   "unique: the points lie on one plane (or the two cameras share a "
                                   "centre); use a scene with depth and move the camera")


def conjugate_to_rotation(H: np.ndarray) -> bool:
    """Whether the homography ``H`` is ``K2 R K1^-1`` (a camera turning about its centre): scaled to
    determinant 1, its three eigenvalues all have modulus 1 (within 1 %)."""
    determinant = np.linalg.det(H)
    if not np.isfinite(determinant) or determinant == 0:
        return False
    eigenvalues = np.abs(np.linalg.eigvals(H / np.cbrt(determinant)))
    return bool(np.all(np.abs(eigenvalues - 1.0) < 0.01))


def is_rotation_homography(x1: np.ndarray, x2: np.ndarray) -> bool:
    """Whether the least-squares homography of all the pairs (``cv2.findHomography``) is a rotation's."""
    import cv2

    H, _ = cv2.findHomography(x1, x2, 0)
    return H is not None and conjugate_to_rotation(H)


@functools.lru_cache(maxsize=64)
def fixed_samples(population: int, size: int, count: int) -> np.ndarray:
    """``count`` samples of ``size`` distinct indices of ``range(population)``, fixed seed (cached)."""
    samples = random_samples(np.random.default_rng(0), population, size, count)
    samples.flags.writeable = False
    return samples


def distance_from_best_line(x: np.ndarray, mask: np.ndarray) -> float:
    """RMS distance (px) of the points ``x[mask]`` ``(N, 2)`` from their best line, without copying them: the
    square root of the smaller eigenvalue of their 2 x 2 covariance, in closed form. The number
    :func:`check_collinear` computes by an SVD, to ~1e-16 of the largest over the smallest spread (plenty to
    screen against a threshold of 0.01 px or more)."""
    return float(_distance_from_best_line_kernel(x, mask))


def homography_share(x1: np.ndarray, x2: np.ndarray, picks: np.ndarray, tolerance_px: float) -> float:
    """The largest fraction of the pairs ``(N, 2)`` that one 4-point homography, of the samples ``picks``
    ``(B, 4)``, maps within ``tolerance_px`` in image 2 (both point sets Hartley-normalized first).

    A quick RANSAC screen (no refinement): if one homography explains 90 % of the pairs, 20 samples all
    miss an all-inlier sample with probability (1 - 0.9^4)^20 < 1e-9, so a small share here (with a looser
    tolerance, ``SCREEN_TOLERANCE``) means the pairs are not degenerate. It stands in front of the model
    selection (GRIC, which fits a homography with ``cv2.findHomography``) because that call costs more than
    the rest of our RANSAC on easy input. Each homography solves ``h9 = 1`` (an 8 x 8 solve); a singular
    sample (repeated points) has the whole answer come from ``homography_share_reference``, whose null
    vectors take any sample.
    """
    share = float(_homography_share_kernel(x1, x2, picks, tolerance_px))
    if share < 0:  # a singular 4-point sample (repeated points): the reference's null vectors
        share = homography_share_reference(x1, x2, picks, tolerance_px)
    return share


def robust_homography(x1: np.ndarray, x2: np.ndarray, tolerance_px: float) -> np.ndarray | None:
    """``cv2.findHomography`` by RANSAC (transfer error within ``tolerance_px``), then twice least squares on
    its inliers.

    OpenCV's own refinement after RANSAC stops early: on a noisy plane its H leaves Sampson errors ~25 %
    larger than the least-squares H of the same inliers, enough to tip the model selection.
    """
    import cv2

    # GRIC picks H only when it explains ~3/4 of the pairs or more: 30 samples of 4 all miss such an H with
    # probability (1 - 0.75^4)^30 < 1e-4 (and more samples cost more than the rest of RANSAC on easy input)
    H, mask = cv2.findHomography(x1, x2, cv2.RANSAC, tolerance_px, maxIters=30, confidence=0.999)
    for _ in range(2):
        if H is None or mask is None or int(mask.sum()) < 4 or mask.mean() < SCREEN_SHARE:
            return H  # an H of under 60 % of the pairs loses the selection, refined or not (it needs ~3/4)
        refit, _ = cv2.findHomography(x1[mask.ravel() > 0], x2[mask.ravel() > 0], 0)
        if refit is None:
            return H
        H = refit
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            mapped = to_homogeneous(x1) @ H.T
            transfer = np.hypot(mapped[:, 0] / mapped[:, 2] - x2[:, 0],
                                mapped[:, 1] / mapped[:, 2] - x2[:, 1])
        mask = (transfer <= tolerance_px).astype(np.uint8)
    return H


def rotation_explains(H: np.ndarray, x1: np.ndarray, x2: np.ndarray, sigma: float) -> bool:
    """Whether the rotation-conjugate homography nearest ``H`` (its eigenvalues scaled to modulus 1,
    ``V diag(w / |w|) V^-1``) still explains the pairs ``(N, 2)`` within the noise ``sigma``.

    The eigenvalue test alone (:func:`conjugate_to_rotation`, 1 %) cannot tell some planes from a
    turn of the camera: a plane's homography ``K2 (R - t n^T / d) K1^-1`` may be within 1 % of a
    rotation's. Whether 1 % matters depends on the noise: here it is measured against the residuals.
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        w, V = np.linalg.eig(H / np.cbrt(np.linalg.det(H)))
        try:
            rotation = np.real(V @ np.diag(w / np.abs(w)) @ np.linalg.inv(V))
        except np.linalg.LinAlgError:
            return False
        cap = GRIC_LAMBDA3 * (GRIC_R - GRIC_H[0])
        cost = np.minimum((homography_sampson_distance(rotation, x1, x2) / sigma) ** 2, cap)
        base = np.minimum((homography_sampson_distance(H, x1, x2) / sigma) ** 2, cap)
    extra = float(np.mean(np.nan_to_num(cost, nan=cap) - np.nan_to_num(base, nan=cap)))
    return extra <= ROTATION_EXTRA_COST


def check_not_degenerate(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, inliers: np.ndarray,
                         threshold_px: float, distances: np.ndarray | None = None) -> None:
    """Raise when the inliers lie on a line, or when a homography explains the matches as well as F (one
    plane, or no baseline).

    A homography ``H`` maps image 1 to image 2 for points on one plane, and for any scene when the
    cameras share a centre (``H = K2 R K1^-1``); then F is not determined (a whole family of F fits
    equally well). Which model the matches support is decided by Torr's GRIC (:func:`gric`), not by
    a share under a threshold (at 1 px noise the transfer error of a plane's points passes 2 px for
    a third of them). The noise ``sigma`` is measured from F's Sampson distances of all matches
    (:func:`noise_sigma`, robust to outliers and to the RANSAC threshold); the pairs F explains within
    3 sigma (at most 300, spread over the list) are the data; ``H`` is fitted to them by
    ``cv2.findHomography`` (RANSAC at 3.5 sigma of transfer error, then least squares on its inliers,
    :func:`robust_homography`); the residuals are the Sampson errors of F (:func:`sampson_distance`) and of H
    (:func:`homography_sampson_distance`). Degenerate when ``GRIC(H) <= GRIC(F)``. A homography
    conjugate to a rotation has eigenvalues of equal modulus: that says zero baseline. A fast
    4-point screen (:func:`homography_share`) skips the selection when no homography comes
    near most pairs. Reference: H&Z section 11.9 (degeneracies); Torr (CVPR 1997; Phil. Trans. 1998);
    Chum, Werner and Matas, "Two-view geometry estimation unaffected by a dominant plane", CVPR 2005.
    """
    for name, x in (("x1", x1), ("x2", x2)):  # compiled screen; the readable check decides near the line
        if distance_from_best_line(x, inliers) <= 1.01 * threshold_px:
            check_collinear(x[inliers], name, threshold_px)
    if distances is None:  # F's Sampson distances of all the pairs (RANSAC passes those it has)
        with np.errstate(divide="ignore", invalid="ignore"):
            distances = sampson_distance(F, x1, x2)
    sigma = noise_sigma(distances, start_px=threshold_px)
    consistent = np.flatnonzero(distances <= max(3.0 * sigma, threshold_px))
    if len(consistent) < SAMPLE_SIZE:
        consistent = np.flatnonzero(inliers)
    spread = np.linspace(0, len(consistent) - 1, 300).round().astype(int) if len(consistent) > 300 \
        else np.arange(len(consistent))
    chosen = consistent[spread]  # at most 300, evenly over the list (steps >= 1 apart: no repeats)
    a, b = x1[chosen], x2[chosen]
    tolerance = max(SCREEN_TOLERANCE * 2.0 * threshold_px, SCREEN_SIGMAS * sigma)
    share = homography_share(a, b, fixed_samples(len(a), 4, 20), tolerance) if len(a) >= 8 else 1.0
    if share < SCREEN_SHARE:
        return  # no homography comes near most pairs even far looser: it cannot win the model selection
    H = robust_homography(a, b, 3.5 * sigma)
    if H is None:
        return
    residuals_F, residuals_H = sampson_distance(F, a, b), homography_sampson_distance(H, a, b)
    close = residuals_H <= 3.0 * sigma
    # most pairs follow H: F's spare freedom has absorbed part of the noise, take H's too (2 dof, cut at 3)
    if close.mean() >= 0.5:
        spread = np.mean(residuals_H[close] ** 2) / (2.0 * truncated_variance_factor(3.0, 2))
        sigma = max(sigma, float(np.sqrt(spread)))
    gric_F = gric(residuals_F, sigma, *GRIC_F)
    gric_H = gric(residuals_H, sigma, *GRIC_H)
    if gric_H > gric_F:
        return
    finding = (f"one homography explains the {len(chosen)} matches tested as well as F (Torr's GRIC: H "
               f"{gric_H:.0f} <= F {gric_F:.0f}, noise {sigma:.2f} px)")
    if conjugate_to_rotation(H) and rotation_explains(H, a, b, sigma):
        raise ZeroBaseline("x1", f"{finding}, and it is (close to) a rotation: the two cameras share their "
                                 "centre (zero baseline), so there is no parallax and F (and t) are not "
                                 "determined; move the camera between the photos")
    raise CoplanarPoints("x1", f"{finding}: the points lie on one plane (or the cameras hardly moved), so F "
                               "is not determined; include points off the plane")


__all__ = ["ROTATION_EXTRA_COST", "SCREEN_SHARE", "SCREEN_SIGMAS", "SCREEN_TOLERANCE", "check_collinear",
           "check_determined", "check_not_degenerate", "conjugate_to_rotation", "distance_from_best_line",
           "fixed_samples", "homography_share", "is_rotation_homography", "robust_homography",
           "rotation_explains"]
