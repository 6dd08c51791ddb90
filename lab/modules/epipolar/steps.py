"""The steps of the epipolar module, in pipeline order, each with its result: what the lesson walks through.

Features and matches (SIFT, the ratio test), F by the normalized 8-point algorithm and by RANSAC, the
epipolar lines, E, its four poses and the one in front of both cameras, the pose polished, and the
points triangulated and refined. Each step checks its input, calls the math of its topic module
(:mod:`.fundamental`, :mod:`.ransac`, :mod:`.degeneracy`, :mod:`.lines`, :mod:`.essential`,
:mod:`.matching`) and returns its values and metrics. See the package's docstring for the state names.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np

from lab.core import (Cameras, Curve, Image, ImageSet, InvalidValue, PointCloud, Points2D, Range, Segments2D,
                      Warnings, metric, step_result)
from lab.geometry.camera import as_intrinsics, pixels_to_normalized
from lab.geometry.rotations import rotation_angle_deg
from lab.geometry.triangulation import (point_depths, projection_matrix, reprojection_residuals,
                                        triangulate_dlt)
from lab.geometry.triangulation import refine_points as refine_point_positions
from lab.modules.epipolar._checks import (SAMPLE_SIZE, DegenerateInput, TooFewMatches,
                                          check_matrix, check_pair, check_pose,
                                          check_rotation_translation, check_two_images, inliers_or_all,
                                          intrinsics_for, rotation_problem)
from lab.modules.epipolar.degeneracy import check_determined, check_not_degenerate
from lab.modules.epipolar.distances import sampson_distance, symmetric_epipolar_distance
from lab.modules.epipolar.essential import (CANDIDATE_NAMES, cheirality_counts, essential_candidates,
                                            median_parallax_deg, polish_pose)
from lab.modules.epipolar.fundamental import eight_point, numerical_rank
from lab.modules.epipolar.lines import draw_lines, epipoles, finite_epipoles
from lab.modules.epipolar.matching import nearest_neighbours
from lab.modules.epipolar.ransac import ransac_fundamental


# ----------------------------------------------------------------------------------------------------
# 1. Features
# ----------------------------------------------------------------------------------------------------
#: OpenCV's SIFT reports keypoints this many pixels right of and below where they are (pixel centres at
#: integer coordinates): its first octave is the image upsampled 2x by a centre-aligned ``cv2.resize``,
#: but coordinates found there are halved as if the grids were corner-aligned (a Gaussian blob centred at
#: (50, 60) is reported at about (50.24, 60.24)). A shift shared by every keypoint of every image acts like
#: a wrong principal point and tilts the cameras by ``0.25 / f`` radians (0.04 degrees at f = 554 px), so
#: :func:`detect_features` subtracts it; the SfM module reads its keypoints from there.
SIFT_OFFSET_PX = 0.25


@step_result
class FeatureDetection:
    """Result of :func:`detect_features`."""

    keypoints: Points2D
    descriptors: np.ndarray
    warnings: Warnings
    keypoints_image1: int = metric("keypoints found in image 1")
    keypoints_image2: int = metric("keypoints found in image 2")


def detect_features(images: ImageSet, *, max_features: Annotated[int, Range(0, 50000)] = 4000,
                    contrast_threshold: Annotated[float, Range(0.001, 0.5)] = 0.04) -> FeatureDetection:
    """SIFT keypoints and descriptors in both images (OpenCV's ``cv2.SIFT_create``).

    Keypoints are extrema of the difference-of-Gaussians scale space, kept where their contrast
    exceeds ``contrast_threshold`` and away from edges; each gets a 128-D histogram of gradient
    orientations around it, rotated to its dominant orientation and scaled to its scale, so it
    can be matched across viewpoints. Run on the 8-bit grayscale image. OpenCV's coordinates are
    moved by ``-SIFT_OFFSET_PX`` in x and y, to undo its quarter-pixel bias (:data:`SIFT_OFFSET_PX`):
    a blob centred on pixel (x, y) is reported at (x, y).

    Args:
        max_features: keep the strongest this many keypoints per image (0: all).
        contrast_threshold: reject weak extrema (OpenCV's contrastThreshold; lower finds more).

    Returns ``keypoints`` (Points2D, ``view`` 0 for image 1 then 1 for image 2) and
    ``descriptors`` ``(N, 128)`` float32 in the same order.

    Reference: D. Lowe, IJCV 60(2), 2004, sections 3-6.
    """
    import cv2

    images = check_two_images(images)
    sift = cv2.SIFT.create(nfeatures=int(max_features), contrastThreshold=float(contrast_threshold))
    xy, view, descriptors, warnings, counts = [], [], [], [], []
    for index, image in enumerate(images.images):
        gray8 = np.clip(image.gray() * 255.0 + 0.5, 0, 255).astype(np.uint8)
        found, described = sift.detectAndCompute(gray8, None)
        points = np.array([k.pt for k in found], dtype=np.float64).reshape(-1, 2) - SIFT_OFFSET_PX
        described = np.zeros((0, 128), np.float32) if described is None else described.astype(np.float32)
        xy.append(points)
        view.append(np.full(len(points), index))
        descriptors.append(described)
        counts.append(len(points))
        if len(points) < SAMPLE_SIZE:
            warnings.append(f"{images.names[index]}: only {len(points)} keypoints; lower the contrast "
                            "threshold")
    keypoints = Points2D(np.concatenate(xy), view=np.concatenate(view), image="images")
    return FeatureDetection(keypoints, np.concatenate(descriptors), tuple(warnings), counts[0], counts[1])


def keypoint_locations(keypoints: Points2D) -> np.ndarray:
    """For each keypoint, the index of the first keypoint at the same pixel of the same image ``(N,)``.

    SIFT gives an extremum one keypoint per orientation-histogram peak within 80% of the highest
    (Lowe 2004, section 5), so one location may come several times, each time with another descriptor.
    Keypoints whose entry is their own index are the locations; the others are their repeats.
    """
    xy = np.asarray(keypoints.xy, dtype=np.float64).reshape(-1, 2)
    if not len(xy):
        return np.zeros(0, dtype=np.int64)
    view = np.zeros(len(xy)) if keypoints.view is None else np.asarray(keypoints.view, dtype=np.float64)
    _, first, inverse = np.unique(np.column_stack([view, xy]), axis=0, return_index=True,
                                  return_inverse=True)
    return first[inverse.reshape(-1)].astype(np.int64)


# ----------------------------------------------------------------------------------------------------
# 2. Matching
# ----------------------------------------------------------------------------------------------------
@step_result
class Matching:
    """Result of :func:`match_features`."""

    matches: np.ndarray
    x1: np.ndarray
    x2: np.ndarray
    warnings: Warnings
    num_matches: int = metric("matches kept")
    rejected_by_ratio: int = metric("nearest neighbours rejected by the ratio test")
    rejected_by_mutual: int = metric("nearest neighbours rejected by the mutual check")
    repeated: int = metric("matches of two locations already matched (SIFT's repeated keypoints)")


def match_features(keypoints: Points2D, descriptors: np.ndarray, *,
                   ratio: Annotated[float, Range(0.05, 1.0)] = 0.8, mutual: bool = True) -> Matching:
    """Match descriptors of image 1 to image 2: nearest neighbour, Lowe's ratio test, mutual check.

    Each descriptor of image 1 takes its nearest neighbour among those of image 2 (Euclidean). The
    ratio test keeps it only if the nearest is clearly nearer than the second nearest,
    ``d1 < ratio * d2``: a distinctive match (Lowe found that 0.8 rejects 90 % of the wrong
    matches and 5 % of the right ones). The mutual check keeps it only if the descriptor of image
    1 is also the nearest neighbour of its match (a cross check). Written here with NumPy
    (:func:`nearest_neighbours`: float32 distances, re-checked in float64 where float32 cannot decide,
    so the float64 answer of :func:`nearest_neighbours_reference`, several times faster); OpenCV does
    the same with ``cv2.BFMatcher(cv2.NORM_L2)``:
    ``knnMatch(d1, d2, k=2)`` for the ratio test and ``crossCheck=True`` for the mutual check.

    Args:
        ratio: largest allowed ratio of nearest to second-nearest distance (1: no ratio test).
        mutual: keep only matches that are each other's nearest neighbour.

    SIFT may give one location several keypoints (one per strong orientation, Lowe section 5), each
    with its own descriptor, and more than one of them may match: a match is made between locations
    (:func:`keypoint_locations`: each keypoint stands for the first keypoint at its pixel), once, so a
    pixel is one observation and no two tracks or triangulated points share it (issue 19: 100 of SfM's
    3980 points were exact duplicates).

    Returns ``matches`` ``(M, 2)`` (indices into ``keypoints``: image 1, image 2; the first keypoint
    at each location), sorted by the image-1 keypoint, and the matched pixels ``x1``, ``x2`` ``(M, 2)``.

    Reference: D. Lowe, IJCV 60(2), 2004, section 7.1.
    """
    if not isinstance(keypoints, Points2D) or keypoints.view is None:
        raise InvalidValue("keypoints", "expected Points2D with a view (0 or 1) per keypoint")
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2 or len(descriptors) != len(keypoints):
        raise InvalidValue("descriptors", f"expected one row per keypoint ({len(keypoints)}), got shape "
                                          f"{descriptors.shape}")
    if descriptors.dtype.kind == "f" and not np.all(np.isfinite(descriptors)):
        raise InvalidValue("descriptors", "contains NaN or infinite entries")
    index1 = np.flatnonzero(keypoints.view == 0)
    index2 = np.flatnonzero(keypoints.view == 1)
    warnings: list[str] = []
    if len(index1) == 0 or len(index2) == 0:
        empty = np.zeros((0, 2))
        return Matching(np.zeros((0, 2), dtype=np.int64), empty, empty.copy(),
                        ("no keypoints in one of the images: nothing to match",), 0, 0, 0, 0)
    first, d1, d2, back = nearest_neighbours(descriptors[index1], descriptors[index2])
    passes_ratio = d1 < ratio * d2 if ratio < 1.0 else np.ones(len(index1), dtype=bool)
    is_mutual = back[first] == np.arange(len(index1))
    keep = passes_ratio & (is_mutual if mutual else True)
    nearest = np.column_stack([index1[keep], index2[first[keep]]]).astype(np.int64)
    matches = np.unique(keypoint_locations(keypoints)[nearest], axis=0).reshape(-1, 2)
    if len(matches) < SAMPLE_SIZE:
        warnings.append(f"only {len(matches)} matches: F needs at least {SAMPLE_SIZE}; raise the ratio or "
                        "detect more features")
    rejected_by_mutual = int(np.sum(passes_ratio & ~is_mutual)) if mutual else 0
    return Matching(matches, keypoints.xy[matches[:, 0]], keypoints.xy[matches[:, 1]], tuple(warnings),
                    len(matches), int(np.sum(~passes_ratio)), rejected_by_mutual, len(nearest) - len(matches))


# ----------------------------------------------------------------------------------------------------
# 3. The 8-point algorithm (a lesson step)
# ----------------------------------------------------------------------------------------------------
def estimate_fundamental_8point(x1: np.ndarray, x2: np.ndarray, *,
                                normalize: bool = True) -> Annotated[np.ndarray, "F"]:
    """The fundamental matrix of all matches by the (normalized) 8-point algorithm, rank 2 enforced.

    Each match gives one linear equation ``x2^T F x1 = 0`` in the nine entries of F::

        [u2 u1, u2 v1, u2, v2 u1, v2 v1, v2, u1, v1, 1] . f = 0

    ``f`` is the right singular vector of the stacked ``A`` with the smallest singular value (the
    least-squares solution with ``|f| = 1``); F is then made singular (:func:`enforce_rank2`).
    With ``normalize`` both point sets are first moved to their centroid and scaled to mean
    distance sqrt(2) (``T1``, ``T2``, :func:`lab.geometry.homogeneous.hartley_normalization`) and
    ``F = T2^T F_n T1``: in pixels the columns of ``A`` differ by ~10^5 in scale, ``A`` is badly
    conditioned and the solution is poor (Hartley 1997); normalized, it is as good as iterative
    methods on clean data. Every match counts: on real matches the outliers spoil it (RANSAC next).

    Args:
        normalize: apply Hartley's normalization before solving (off: to see why it matters).

    Returns F ``(3, 3)``, rank 2, unit Frobenius norm. Corresponds to
    ``cv2.findFundamentalMat(x1, x2, cv2.FM_8POINT)`` (which always normalizes and scales
    ``F[2, 2] = 1``).

    Reference: H&Z section 11.1 and algorithm 11.1; R. Hartley, TPAMI 19(6), 1997.
    """
    x1, x2 = check_pair(x1, x2)
    check_determined(x1, x2)  # 8 independent equations: not on one line, one plane, or seen from one centre
    return eight_point(x1, x2, normalize=normalize)


# ----------------------------------------------------------------------------------------------------
# 4. RANSAC
# ----------------------------------------------------------------------------------------------------
@step_result
class RansacFundamental:
    """Result of :func:`estimate_fundamental_ransac`."""

    F: np.ndarray
    inliers: np.ndarray
    ransac_trace: Curve
    num_inliers: int = metric("matches consistent with F")
    inlier_ratio: float = metric("fraction of the matches that are inliers")
    iterations: int = metric("hypotheses drawn (the adaptive N)")
    sampson_rms_px: float = metric("RMS Sampson distance of the inliers", unit="px")
    rank_of_F: int = metric("numerical rank of F (2 for a fundamental matrix)")


def estimate_fundamental_ransac(x1: np.ndarray, x2: np.ndarray, *,
                                threshold_px: Annotated[float, Range(0.01, 100.0)] = 1.0,
                                confidence: Annotated[float, Range(0.5, 0.999999)] = 0.99,
                                max_iterations: Annotated[int, Range(1, 100000)] = 5000,
                                error: Literal["sampson", "epipolar"] = "sampson", refine: bool = True,
                                check_degenerate: bool = True, rng: np.random.Generator) -> RansacFundamental:
    """Robust F: RANSAC over 8-point samples with the adaptive iteration count, then a refit on the inliers.

    Repeat: draw 8 matches at random, solve the normalized 8-point algorithm on them
    (:func:`eight_point`, a batch of samples at once: 8, 16, 32 ... 256), count the matches whose
    error is below ``threshold_px``; keep the F with the most inliers. Each new best is first
    optimized locally (LO-RANSAC: refit on all its inliers while that gains inliers), then the
    number of samples needed is recomputed from its inlier ratio ``w``:
    ``N = log(1 - confidence) / log(1 - w^8)`` (:func:`lab.geometry.robust.ransac_iterations`),
    capped by ``max_iterations``; sampling stops once ``N`` samples are drawn. With ``refine`` the
    final F is refit on its inliers by Sampson-weighted least squares (close to the F of least
    Sampson error). Last, the inliers are checked for degeneracy
    (:func:`~lab.modules.epipolar.degeneracy.check_not_degenerate`): on one line, on one plane, or
    seen from one centre, F is not determined and the step says so instead of answering.

    Args:
        threshold_px: largest error of an inlier, in pixels.
        confidence: probability that at least one sample is all inliers (sets the adaptive N).
        max_iterations: most samples drawn.
        error: "sampson" (first-order geometric error, :func:`sampson_distance`) or "epipolar"
            (the larger of the two point-to-epipolar-line distances, what ``cv2.FM_RANSAC`` thresholds).
        refine: refit F on the inliers by iteratively Sampson-weighted least squares.
        check_degenerate: refuse degenerate input (a plane, a line, no baseline).

    Returns F ``(3, 3)`` (rank 2, unit norm), ``inliers`` ``(M,)`` bool and ``ransac_trace`` (best
    inlier count and the bound N after each batch). Corresponds to
    ``cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, threshold_px, confidence, max_iterations)``,
    which samples 7 matches (the 7-point algorithm) instead of 8.

    The loop is :func:`~lab.modules.epipolar.ransac.ransac_fundamental`: compiled, one call per batch, per
    new best and per refit (:mod:`.ransac`); the tests run it on the readable references as well
    (``reference.RANSAC_REFERENCE``) and get the same answer.

    Reference: H&Z section 4.7.1 (adaptive RANSAC, algorithm 4.5) and algorithm 11.4; Fischler and
    Bolles (1981); Chum, Matas and Kittler, "Locally optimized RANSAC", DAGM 2003.
    """
    x1, x2 = check_pair(x1, x2)
    fit = ransac_fundamental(x1, x2, threshold_px=threshold_px, confidence=confidence,
                             max_iterations=max_iterations, error=error, refine=refine, rng=rng)
    num_inliers = int(np.count_nonzero(fit.inliers))
    if num_inliers < SAMPLE_SIZE:
        raise TooFewMatches("x1", f"only {num_inliers} inliers within {threshold_px:g} px; raise "
                                  "threshold_px")
    if check_degenerate:  # with the Sampson distances of every match, which RANSAC has
        check_not_degenerate(fit.F, x1, x2, fit.inliers, threshold_px, fit.distances)
    trace = Curve(fit.trace[0].copy(), fit.trace[1:].copy(), kind="line",
                  title=f"RANSAC: {fit.best_count} inliers after {fit.drawn} samples", xlabel="samples drawn",
                  ylabel="count", labels=("best inlier count", "samples needed (N)"))
    return RansacFundamental(fit.F, fit.inliers, trace, num_inliers, num_inliers / len(x1), fit.drawn,
                             float(np.sqrt(np.mean(fit.distances[fit.inliers] ** 2))), numerical_rank(fit.F))


# ----------------------------------------------------------------------------------------------------
# 5. Epipolar lines and epipoles
# ----------------------------------------------------------------------------------------------------
@step_result
class EpipolarDrawing:
    """Result of :func:`compute_epipolar_lines`."""

    epipolar_lines: Segments2D
    line_points: Points2D
    epipoles: np.ndarray
    epipole_points: Points2D
    sampson_rms_px: float = metric("RMS Sampson distance of the inliers", unit="px")
    symmetric_rms_px: float = metric("RMS symmetric epipolar distance of the inliers", unit="px")
    rank_of_F: int = metric("numerical rank of F")
    lines_drawn: int = metric("inliers whose lines are drawn")


def compute_epipolar_lines(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, images: ImageSet,
                           inliers: np.ndarray | None = None, *,
                           num_lines: Annotated[int, Range(1, 500)] = 30) -> EpipolarDrawing:
    """Epipolar lines of a sample of inliers, the epipoles, and how well F fits the inliers.

    A point ``x1`` in image 1 must be seen in image 2 on its epipolar line ``l2 = F x1``, and
    ``x2`` in image 1 on ``l1 = F^T x2`` (:func:`epipolar_lines`, ``cv2.computeCorrespondEpilines``).
    All lines of an image pass through its epipole (:func:`epipoles`), the image of the other
    camera's centre. ``num_lines`` inliers spread evenly over the match list are drawn, each line
    and its two points in one colour. The metrics say how well F explains the inliers:
    the RMS Sampson distance and the RMS symmetric epipolar distance.

    Args:
        num_lines: how many inliers to draw lines for.

    Reference: H&Z sections 9.1-9.2 (result 9.5: ``l' = F x``; result 9.8: ``F e = 0``,
    ``F^T e' = 0``), 11.4.3 (the distances).
    """
    F = check_matrix(F, "F")
    x1, x2 = check_pair(x1, x2, minimum=1)
    images = check_two_images(images)
    mask = inliers_or_all(inliers, len(x1))
    chosen = np.flatnonzero(mask)
    if len(chosen) > num_lines:
        chosen = chosen[np.linspace(0, len(chosen) - 1, num_lines).round().astype(int)]
    segments, points = draw_lines(F, x1[chosen], x2[chosen], images)
    pair = epipoles(F)
    epipole_points = finite_epipoles(pair)
    sampson = sampson_distance(F, x1[mask], x2[mask])
    symmetric = symmetric_epipolar_distance(F, x1[mask], x2[mask])
    return EpipolarDrawing(segments, points, pair, epipole_points, float(np.sqrt(np.mean(sampson**2))),
                           float(np.sqrt(np.mean(symmetric**2))), numerical_rank(F), len(chosen))


# ----------------------------------------------------------------------------------------------------
# 6. The essential matrix
# ----------------------------------------------------------------------------------------------------
def estimate_essential(F: np.ndarray, images: ImageSet, K1: np.ndarray | None = None,
                       K2: np.ndarray | None = None) -> Annotated[np.ndarray, "E"]:
    """The essential matrix ``E = K2^T F K1``, projected onto the essential matrices.

    F relates pixels; E relates normalized image coordinates ``K^-1 x``, so ``E = K2^T F K1``. An
    essential matrix ``[t]_x R`` has two equal singular values and a zero one (H&Z result 9.17);
    the product from an estimated F does not, so it is replaced by the nearest essential matrix in
    Frobenius norm, ``U diag(1, 1, 0) V^T`` (H&Z section 11.7.3; the scale of E is arbitrary and
    (1, 1, 0) goes with ``|t| = 1``). OpenCV has no single call: ``cv2.findEssentialMat`` estimates
    E directly from normalized points (the 5-point algorithm) instead of going through F.

    Returns E ``(3, 3)`` with singular values (1, 1, 0).

    Reference: H&Z section 9.6 (eq. 9.12, result 9.17), section 11.7.3.
    """
    F = check_matrix(F, "F")
    K1, K2 = intrinsics_for(images, K1, K2)
    U, _, Vt = np.linalg.svd(K2.T @ F @ K1)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


# ----------------------------------------------------------------------------------------------------
# 7. The four poses of E, and the one in front of both cameras (lesson steps)
# ----------------------------------------------------------------------------------------------------
def decompose_essential(E: np.ndarray) -> Annotated[np.ndarray, "candidates"]:
    """The four relative poses an essential matrix admits, ``(4, 3, 4)`` stacked ``[R | t]`` (``|t| = 1``).

    ``E = [t]_x R`` fixes ``t`` only up to sign and ``R`` up to a half turn about ``t``, so there
    are four candidates ``(R1, t), (R2, t), (R1, -t), (R2, -t)`` (:func:`essential_candidates`).
    Corresponds to ``cv2.decomposeEssentialMat(E)`` -> ``R1, R2, t``.

    Reference: H&Z section 9.6.2, result 9.19 and figure 9.12.
    """
    return essential_candidates(E)


def _candidates_of(value: Any) -> np.ndarray:
    """``(4, 3, 4)`` candidates; an essential matrix ``(3, 3)`` is decomposed first (callers that hold E)."""
    array = np.asarray(value, dtype=np.float64)
    if array.shape == (3, 3):
        return essential_candidates(array)
    if array.shape != (4, 3, 4):
        raise InvalidValue("candidates", "expected the four [R | t] of decompose_essential, shape (4, 3, "
                                         f"4), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidValue("candidates", "contains NaN or infinite entries")
    for index, pose in enumerate(array):
        problem = rotation_problem(pose[:, :3])
        if problem:
            raise InvalidValue("candidates", f"candidate {index} ({CANDIDATE_NAMES[index]}): {problem} (each "
                                             "of the four must be [R | t] with a rotation R: R^T R = I, "
                                             "det R = +1)")
    return array


def recover_pose(candidates: np.ndarray, x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                 inliers: np.ndarray | None = None, *,
                 candidate: Literal["cheirality", "R1 t", "R2 t", "R1 -t", "R2 -t"] = "cheirality",
                 ) -> Annotated[np.ndarray, "pose"]:
    """The relative pose ``[R | t]`` of camera 2: of E's four candidates, the one with the points in front.

    Triangulate the inliers (normalized by ``K^-1``) with each candidate ``[R | t]`` of
    :func:`decompose_essential` and keep the one that puts the most of them in front of both
    cameras (positive depth in camera 1, ``Z`` of ``X``, and in camera 2, ``Z`` of ``R X + t``: the
    cheirality test). For a correct E one candidate has all of them in front (bar noise on very
    distant points); ``(R, -t)`` puts them all behind both cameras and the two "twisted" ones behind
    one camera.

    Args:
        candidate: "cheirality" (the test above), or one of the four by name, to see what a wrong
            choice does to the rest of the pipeline.

    ``candidates`` may also be an essential matrix ``(3, 3)``, decomposed first. Returns ``pose``
    ``(3, 4)`` = ``[R | t]`` with ``X_2 = R X_1 + t`` and ``|t| = 1`` (the scale of a two-view
    reconstruction is unknown). Corresponds to ``cv2.recoverPose(E, x1, x2, K, mask=inliers)`` (one K
    for both views; which also drops points more than 50 units away from the vote).

    Reference: H&Z section 9.6.3 (figure 9.12) and section 12.2 (triangulation).
    """
    candidates = _candidates_of(candidates)
    x1, x2 = check_pair(x1, x2, minimum=1)
    mask = inliers_or_all(inliers, len(x1))
    if candidate != "cheirality":
        return candidates[CANDIDATE_NAMES.index(candidate)].copy()
    if not mask.any():
        raise TooFewMatches("inliers", "no inliers to test the four poses with")
    K1, K2 = as_intrinsics(K1), as_intrinsics(K2)
    n1, n2 = pixels_to_normalized(x1[mask], K1), pixels_to_normalized(x2[mask], K2)
    counts = cheirality_counts(candidates, n1, n2)
    best = int(np.argmax(counts))
    if counts[best] == 0:
        raise DegenerateInput("candidates", "no candidate pose puts any point in front of both cameras: E "
                                            "does not fit these matches")
    return candidates[best].copy()


# ----------------------------------------------------------------------------------------------------
# 8. Refining the pose
# ----------------------------------------------------------------------------------------------------
@step_result
class RefinedPose:
    """Result of :func:`refine_pose`."""

    R: np.ndarray
    t: np.ndarray
    warnings: Warnings
    sampson_rms_px: float = metric("RMS Sampson distance of the inliers to E(R, t), after", unit="px")
    sampson_rms_start_px: float = metric("the same for the starting pose", unit="px")
    rotation_change_deg: float = metric("angle between the starting and the refined rotation", unit="deg")
    translation_change_deg: float = metric("angle between the starting and the refined t", unit="deg")
    median_parallax_deg: float = metric("median angle between the two rays of an inlier", unit="deg")


def refine_pose(pose: np.ndarray, x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                inliers: np.ndarray | None = None, *,
                iterations: Annotated[int, Range(0, 200)] = 30) -> RefinedPose:
    """Polish ``(R, t)`` on the inliers: minimize their Sampson distances to ``K2^-T [t]_x R K1^-1``.

    F from the 8-point algorithm has 7 degrees of freedom and ignores that the cameras are
    calibrated; a relative pose has 5 (3 for R, 2 for the direction of t). Starting from the
    chosen pose, Levenberg-Marquardt (``scipy.optimize.least_squares``) minimizes the sum of squared
    Sampson distances (:func:`sampson_distance`, in pixels) over ``R = exp([w]_x) R0`` and
    ``t = (t0 + B b) / |t0 + B b|`` (``B`` spans the plane orthogonal to ``t0``): the calibrated
    maximum-likelihood estimate to first order. On well-spread points it moves the pose by hundredths
    of a degree; on nearly degenerate ones (a small or flat scene) it repairs what the 7-parameter F
    got wrong.

    Args:
        iterations: most function evaluations per parameter (0: keep the pose as chosen).

    Returns ``R`` ``(3, 3)`` and ``t`` ``(3,)`` with ``|t| = 1``, and a warning when the median
    parallax (the angle between an inlier's two rays, 0 for points at infinity) is below 1 degree:
    then t's direction is uncertain whatever the method. No single OpenCV call: OpenCV's USAC
    estimators polish E on the inliers in the same spirit.

    Reference: H&Z section 11.4.3 (the Sampson error) and section 11.7.3 (E from calibrated points);
    B. Triggs et al., "Bundle adjustment - a modern synthesis" (2000), section 2.2 (local parameterizations).
    """
    R0, t0 = check_pose(pose)
    x1, x2 = check_pair(x1, x2, minimum=1)
    mask = inliers_or_all(inliers, len(x1))
    K1, K2 = as_intrinsics(K1), as_intrinsics(K2)
    norm = np.linalg.norm(t0)
    if norm == 0:
        raise InvalidValue("pose", "t is zero: the direction of the baseline is undefined")
    t0 = t0 / norm
    a, b = x1[mask], x2[mask]
    R, t, start, final = polish_pose(R0, t0, a, b, K1, K2, iterations)
    parallax = median_parallax_deg(a, b, K1, K2, R)
    warnings: tuple[str, ...] = ()
    if parallax < 1.0:
        warnings = (f"the median parallax is only {parallax:.2f} degrees: the baseline is small compared "
                    "with the depth of the scene, so the direction of t is poorly determined",)
    turn_of_t = float(np.degrees(np.arccos(np.clip(t @ t0, -1.0, 1.0))))
    return RefinedPose(R, t, warnings, float(np.sqrt(np.mean(final**2))), float(np.sqrt(np.mean(start**2))),
                       float(rotation_angle_deg(R0, R)), turn_of_t, parallax)


# ----------------------------------------------------------------------------------------------------
# 9. Triangulation and its refinement
# ----------------------------------------------------------------------------------------------------
def _projections_of(K1: np.ndarray, K2: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    R, t = check_rotation_translation(R, t)
    return np.stack([projection_matrix(as_intrinsics(K1), np.eye(3), np.zeros(3)),
                     projection_matrix(as_intrinsics(K2), R, t)])


def triangulate(x1: np.ndarray, x2: np.ndarray, R: np.ndarray, t: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                inliers: np.ndarray | None = None) -> Annotated[np.ndarray, "points3d_dlt"]:
    """Linear (DLT) triangulation of the inliers with ``P1 = K1 [I | 0]`` and ``P2 = K2 [R | t]`` (refined).

    For each match, the 3D point whose images are ``x1`` and ``x2``: ``x cross (P X) = 0`` gives two
    equations per view, and X is the null vector of the ``4 x 4`` system
    (:func:`lab.geometry.triangulation.triangulate_dlt`). It minimizes an algebraic error, not the
    distance in the images; :func:`refine_points` does that next.

    Returns ``(N, 3)`` points in camera 1's frame, one per inlier in match order, in units of the
    baseline. Corresponds to ``cv2.triangulatePoints(P1, P2, x1.T, x2.T)`` (then dividing by the
    fourth coordinate).

    Reference: H&Z section 12.2.
    """
    x1, x2 = check_pair(x1, x2, minimum=1)
    mask = inliers_or_all(inliers, len(x1))
    P = _projections_of(K1, K2, R, t)
    return triangulate_dlt(P, np.stack([x1[mask], x2[mask]]))


@step_result
class TwoViewReconstruction:
    """Result of :func:`refine_points`."""

    points3d: PointCloud
    cameras: Cameras
    residuals: Segments2D
    reprojection_cost: Curve
    reprojection_rms_px: float = metric("RMS reprojection error after refinement", unit="px")
    reprojection_rms_dlt_px: float = metric("RMS reprojection error of the DLT points", unit="px")
    points: int = metric("triangulated points")
    points_behind: int = metric("points behind either camera (cheirality violated)")


def _colors_at(image: Image, xy: np.ndarray) -> np.ndarray:
    """Colours ``(N, 3)`` of the pixels nearest to ``xy`` (grey images give grey colours)."""
    pixels = image.pixels
    cols = np.clip(np.round(xy[:, 0]).astype(int), 0, image.width - 1)
    rows = np.clip(np.round(xy[:, 1]).astype(int), 0, image.height - 1)
    values = pixels[rows, cols].astype(np.float64)
    return values if values.ndim == 2 else np.repeat(values[:, None], 3, axis=1)


def refine_points(points3d_dlt: np.ndarray, x1: np.ndarray, x2: np.ndarray, R: np.ndarray, t: np.ndarray,
                  K1: np.ndarray, K2: np.ndarray, images: ImageSet, inliers: np.ndarray | None = None, *,
                  iterations: Annotated[int, Range(0, 100)] = 10,
                  residual_scale: Annotated[float, Range(1.0, 1000.0)] = 20.0) -> TwoViewReconstruction:
    """Move each triangulated point to minimize its reprojection error in both images (cameras fixed).

    Levenberg-Marquardt on ``|pi(P1 X) - x1|^2 + |pi(P2 X) - x2|^2`` for every point at once
    (:func:`lab.geometry.triangulation.refine_points`): the maximum-likelihood point under
    Gaussian pixel noise, where the DLT minimized an algebraic error. Then the values to look at: the
    point cloud coloured from image 1, the two cameras, and the residuals drawn magnified.

    Args:
        iterations: most Levenberg-Marquardt iterations (0: keep the DLT points).
        residual_scale: magnification of the residual segments drawn on the images.

    Returns ``points3d`` (PointCloud), ``cameras`` (Cameras: camera 1 at the origin, camera 2 at
    ``(R, t)``, carrying the images), ``residuals`` (Segments2D per observation: observed ->
    observed + scale x (reprojected - observed)), ``reprojection_cost`` (RMS per iteration).
    No single OpenCV call (see :func:`lab.geometry.triangulation.refine_points`).

    Reference: H&Z section 12.5 (the maximum-likelihood criterion) and appendix A6.2.
    """
    x1, x2 = check_pair(x1, x2, minimum=1)
    images = check_two_images(images)
    mask = inliers_or_all(inliers, len(x1))
    X0 = np.asarray(points3d_dlt, dtype=np.float64)
    if X0.shape != (int(mask.sum()), 3):
        raise InvalidValue("points3d_dlt", f"expected one point per inlier ({int(mask.sum())}, 3), got "
                                           f"{X0.shape}")
    P = _projections_of(K1, K2, R, t)
    observed = np.stack([x1[mask], x2[mask]])
    finite = np.all(np.isfinite(X0), axis=1)
    X = np.where(finite[:, None], X0, 0.0)
    visible = np.broadcast_to(finite, observed.shape[:2])
    if finite.any() and iterations > 0:
        refined, history = refine_point_positions(P, observed[:, finite], X[finite], iterations=iterations)
        X[finite] = refined
    else:
        history = np.array([0.0])
        if finite.any():  # the DLT points' RMS reprojection error
            dlt_residual = reprojection_residuals(P, X[finite], observed[:, finite])
            history = np.array([np.sqrt(np.mean(np.sum(dlt_residual**2, axis=2)))])
    residual = reprojection_residuals(P, X, observed)
    residual = np.where(visible[..., None] & np.isfinite(residual), residual, 0.0)
    depth = point_depths(P, X)
    behind = int(np.sum(finite & ~np.all(depth > 0, axis=0)))
    R, t = check_rotation_translation(R, t)
    cameras = Cameras(K=np.stack([as_intrinsics(K1), as_intrinsics(K2)]), R=np.stack([np.eye(3), R]),
                      t=np.stack([np.zeros(3), t]), width=images[0].width, height=images[0].height,
                      image="images")
    n = len(X)
    start = np.concatenate([observed[0], observed[1]])
    residuals = Segments2D(start, start + residual_scale * np.concatenate([residual[0], residual[1]]),
                           view=np.repeat([0, 1], n), image="images")
    cloud = PointCloud(X[finite], colors=_colors_at(images[0], observed[0][finite]))
    cost = Curve(np.arange(len(history), dtype=np.float64), history, kind="line", title="Point refinement",
                 xlabel="iteration", ylabel="RMS reprojection error (px)", labels=("RMS",))
    rms = float(np.sqrt(np.sum(residual**2) / max(2 * int(finite.sum()), 1)))
    return TwoViewReconstruction(cloud, cameras, residuals, cost, rms, float(history[0]), int(finite.sum()),
                                 behind)
