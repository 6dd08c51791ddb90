"""Epipolar geometry of two views, step by step: features, matches, F, E, the relative pose, 3D points.

References: R. Hartley and A. Zisserman, Multiple View Geometry in Computer Vision (2nd ed., 2004),
chapters 9 (epipolar geometry, F and E), 11 (computing F: the normalized 8-point algorithm,
algorithm 11.1; RANSAC, algorithm 11.4) and 12 (triangulation); R. Hartley, "In defense of the
eight-point algorithm", TPAMI 19(6), 1997; M. Fischler and R. Bolles, "Random sample consensus",
CACM 24(6), 1981; D. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 60(2),
2004 (SIFT and the ratio test).

Conventions (DESIGN.md section 3): image 1 is view 0 of ``images`` and image 2 is view 1; camera 1
is the world frame and camera 2 sees ``X_2 = R X_1 + t``; ``x2^T F x1 = 0``; ``E = [t]_x R``,
``F = K2^-T E K1^-1``. The intrinsics are two matrices, ``K1`` and ``K2`` (equal when one camera
took both photos), so a pair from two different cameras needs no special case.

State names (float64 unless said):
    images          ImageSet (2)      the two photos (dataset)
    K1, K2          (3, 3)            camera matrices of image 1 and image 2 (dataset; absent when unknown)
    keypoints       Points2D          SIFT keypoints of both images, ``view`` 0 (image 1) or 1 (image 2)
    descriptors     (N, 128) float32  one descriptor per keypoint
    matches         (M, 2) int        indices into ``keypoints``: [keypoint in image 1, keypoint in image 2]
    x1, x2          (M, 2)            the matched pixels in image 1 and image 2
    F               (3, 3)            fundamental matrix, rank 2, unit Frobenius norm; written by the
                                      8-point step (all matches) and again by RANSAC (the robust estimate):
                                      the later steps read the last one written
    inliers         (M,) bool         RANSAC's inliers (absent before RANSAC runs: every match counts)
    ransac_trace    Curve             best inlier count and the adaptive iteration bound N, per hypothesis
    epipolar_lines  Segments2D        epipolar lines of a sample of inliers, clipped to the images: in
                                      image 2 ``F x1`` (view 1), in image 1 ``F^T x2`` (view 0)
    line_points     Points2D          the sampled inliers themselves, coloured as their lines
    epipoles        (2, 3)            homogeneous unit epipoles: row 0 ``e1`` (``F e1 = 0``, in image 1),
                                      row 1 ``e2`` (``F^T e2 = 0``, in image 2); finite even at infinity
    epipole_points  Points2D          the epipoles that are finite, in pixels (view 0 / 1)
    E               (3, 3)            essential matrix ``K2^T F K1`` projected onto singular values (1, 1, 0)
    candidates      (4, 3, 4)         the four ``[R | t]`` that E admits, (R1, t), (R2, t), (R1, -t),
                                      (R2, -t) (a set: the order follows the signs of E's SVD)
    pose            (3, 4)            ``[R | t]`` of camera 2 chosen by the cheirality test, ``|t| = 1``
    R, t            (3, 3), (3,)      the relative pose after refinement (``X_2 = R X_1 + t``, ``|t| = 1``)
    points3d_dlt    (N, 3)            linear triangulation of the inliers (camera 1 frame, baseline = 1)
    points3d        PointCloud        the refined points, coloured from image 1
    cameras         Cameras (2)       camera 1 at the origin, camera 2 at ``(R, t)``
    residuals       Segments2D        observed pixel -> observed + scale x (reprojected - observed)

Hand-written here, with the OpenCV call each one corresponds to (and is tested against): the
8-point algorithm and rank-2 enforcement (``cv2.findFundamentalMat(..., cv2.FM_8POINT)``), RANSAC
(``cv2.FM_RANSAC``), the Sampson distance (``cv2.sampsonDistance``), epipolar lines
(``cv2.computeCorrespondEpilines``), the decomposition of E (``cv2.decomposeEssentialMat``), the
cheirality test (``cv2.recoverPose``) and triangulation (``cv2.triangulatePoints``, in
:mod:`lab.geometry.triangulation`). SIFT and the homography used to detect degenerate input are
OpenCV's.

The package, in reading order: :mod:`.steps` (the steps above, in pipeline order, with their results);
the math they call, by topic: :mod:`.fundamental` (the 8-point algorithm), :mod:`.distances` (Sampson and
point-to-line distances), :mod:`.ransac` (RANSAC's loop and its fast parts), :mod:`.selection` (noise scale
and GRIC) and :mod:`.degeneracy` (a line, a plane, one centre), :mod:`.lines` (epipolar lines, epipoles),
:mod:`.essential` (the four poses, cheirality, the pose polished), :mod:`.matching` (nearest neighbours);
:mod:`.evaluate` (comparisons with the truth); :mod:`.datasets`. The Numba kernels are in the private
:mod:`._kernels`; each fast function ``x`` has a slow readable ``x_reference`` in :mod:`.reference`, the
tests' oracle (naming as in :mod:`lab.core.kernels`). This file is the only import surface.
"""

from __future__ import annotations

from lab.core import Pipeline
from lab.modules.epipolar._checks import (SAMPLE_SIZE, CollinearPoints, CoplanarPoints, DegenerateInput,
                                          MissingIntrinsics, TooFewMatches, ZeroBaseline)
from lab.modules.epipolar.datasets import correspondences, photos, read_k_file, rendered
from lab.modules.epipolar.degeneracy import (ROTATION_EXTRA_COST, SCREEN_SHARE, SCREEN_SIGMAS,
                                             SCREEN_TOLERANCE, check_not_degenerate, distance_from_best_line,
                                             fixed_samples, homography_share)
from lab.modules.epipolar.distances import epipolar_distances, sampson_distance, symmetric_epipolar_distance
from lab.modules.epipolar.essential import CANDIDATE_NAMES, cheirality_counts, essential_candidates
from lab.modules.epipolar.evaluate import (EVALUATIONS, evaluate_candidates, evaluate_essential,
                                           evaluate_fundamental, evaluate_fundamental_8point,
                                           evaluate_matches, evaluate_pose, evaluate_refined_pose,
                                           evaluate_refinement, evaluate_triangulation)
from lab.modules.epipolar.fundamental import design_matrix, eight_point, enforce_rank2
from lab.modules.epipolar.lines import clip_lines, epipolar_lines, epipoles
from lab.modules.epipolar.matching import nearest_neighbours, two_nearest_scan
from lab.modules.epipolar.ransac import (RansacFit, RansacKernels, inlier_counts, inlier_mask,
                                         local_optimization, minimal_fundamentals, normal_equations,
                                         ransac_fundamental, refit, sampson_distances, sampson_refit)
from lab.modules.epipolar.reference import (RANSAC_REFERENCE, distance_from_best_line_reference,
                                            homographies_4point, homography_share_reference,
                                            inlier_counts_reference, inlier_mask_reference,
                                            local_optimization_reference, minimal_fundamentals_reference,
                                            nearest_neighbours_reference, noise_sigma_reference,
                                            normal_equations_reference, refit_reference,
                                            sampson_refit_reference, two_nearest_scan_reference)
from lab.modules.epipolar.selection import SIGMA_FLOOR_PX, gric, homography_sampson_distance, noise_sigma
from lab.modules.epipolar.steps import (SIFT_OFFSET_PX, EpipolarDrawing, FeatureDetection, Matching,
                                        RansacFundamental, RefinedPose, TwoViewReconstruction,
                                        compute_epipolar_lines, decompose_essential, detect_features,
                                        estimate_essential, estimate_fundamental_8point,
                                        estimate_fundamental_ransac, keypoint_locations, match_features,
                                        recover_pose,
                                        refine_points, refine_pose, triangulate)

#: State names the viewer's interactions (:mod:`lab.viewer.interactions.epipolar`) read by name.
VIEWS = ("images", "K1", "K2", "F", "inliers", "x1", "x2", "E", "candidates", "pose", "R", "t")

PIPELINE = Pipeline.build(
    name="epipolar",
    title="Epipolar geometry",
    summary="Two views step by step: SIFT features, matches with the ratio test, the normalized 8-point "
            "algorithm and RANSAC for F, epipolar lines and epipoles, the essential matrix, the four poses "
            "and the cheirality test, triangulation and its refinement.",
    steps=[detect_features, match_features, estimate_fundamental_8point, estimate_fundamental_ransac,
           compute_epipolar_lines, estimate_essential, decompose_essential, recover_pose, refine_pose,
           triangulate, refine_points],
    datasets=[rendered, correspondences, photos],
    evaluations=EVALUATIONS,
    views=VIEWS,
)

__all__ = [
                                          "CANDIDATE_NAMES",
                                          # evaluation
                                          "EVALUATIONS",
                                          # the pipeline and its steps, in order, with their results
                                          "PIPELINE",
                                          # the readable references (the tests' oracles)
                                          "RANSAC_REFERENCE",
                                          "ROTATION_EXTRA_COST",
                                          # constants
                                          "SAMPLE_SIZE",
                                          "SCREEN_SHARE",
                                          "SCREEN_SIGMAS",
                                          "SCREEN_TOLERANCE",
                                          "SIFT_OFFSET_PX",
                                          "SIGMA_FLOOR_PX",
                                          "VIEWS",
                                          "CollinearPoints",
                                          "CoplanarPoints",
                                          # errors
                                          "DegenerateInput",
                                          "EpipolarDrawing",
                                          "FeatureDetection",
                                          "Matching",
                                          "MissingIntrinsics",
                                          "RansacFit",
                                          "RansacFundamental",
                                          "RansacKernels",
                                          "RefinedPose",
                                          "TooFewMatches",
                                          "TwoViewReconstruction",
                                          "ZeroBaseline",
                                          # degeneracy and model selection
                                          "check_not_degenerate",
                                          "cheirality_counts",
                                          "clip_lines",
                                          "compute_epipolar_lines",
                                          "correspondences",
                                          "decompose_essential",
                                          # the 8-point algorithm, distances, lines and epipoles
                                          "design_matrix",
                                          "detect_features",
                                          "distance_from_best_line",
                                          "distance_from_best_line_reference",
                                          "eight_point",
                                          "enforce_rank2",
                                          "epipolar_distances",
                                          "epipolar_lines",
                                          "epipoles",
                                          # the essential matrix
                                          "essential_candidates",
                                          "estimate_essential",
                                          "estimate_fundamental_8point",
                                          "estimate_fundamental_ransac",
                                          "evaluate_candidates",
                                          "evaluate_essential",
                                          "evaluate_fundamental",
                                          "evaluate_fundamental_8point",
                                          "evaluate_matches",
                                          "evaluate_pose",
                                          "evaluate_refined_pose",
                                          "evaluate_refinement",
                                          "evaluate_triangulation",
                                          "fixed_samples",
                                          "gric",
                                          "homographies_4point",
                                          "homography_sampson_distance",
                                          "homography_share",
                                          "homography_share_reference",
                                          "inlier_counts",
                                          "inlier_counts_reference",
                                          "inlier_mask",
                                          "inlier_mask_reference",
                                          "keypoint_locations",
                                          "local_optimization",
                                          "local_optimization_reference",
                                          "match_features",
                                          "minimal_fundamentals",
                                          "minimal_fundamentals_reference",
                                          # matching
                                          "nearest_neighbours",
                                          "nearest_neighbours_reference",
                                          "noise_sigma",
                                          "noise_sigma_reference",
                                          "normal_equations",
                                          "normal_equations_reference",
                                          "photos",
                                          # RANSAC and its fast parts
                                          "ransac_fundamental",
                                          "read_k_file",
                                          "recover_pose",
                                          "refine_points",
                                          "refine_pose",
                                          "refit",
                                          "refit_reference",
                                          # datasets
                                          "rendered",
                                          "sampson_distance",
                                          "sampson_distances",
                                          "sampson_refit",
                                          "sampson_refit_reference",
                                          "symmetric_epipolar_distance",
                                          "triangulate",
                                          "two_nearest_scan",
                                          "two_nearest_scan_reference",
]
