"""Incremental structure from motion: many photos in, cameras and a sparse point cloud out, one image at a
time.

The classical incremental pipeline (Schönberger and Frahm, "Structure-from-Motion Revisited", CVPR
2016, the COLMAP paper, section 3), as steps (:mod:`lab.modules.sfm.steps`):

1. :func:`detect_all_features` and :func:`match_all_pairs` - SIFT and the ratio test on every pair
   (the epipolar module's :func:`~lab.modules.epipolar.detect_features` and
   :func:`~lab.modules.epipolar.match_features`, reused).
2. :func:`verify_pairs` - geometric verification: F by RANSAC, E, the relative pose by the
   cheirality test (the epipolar module's steps again); the pairs that survive form the view graph,
   each with its inliers and the median triangulation angle of its matches.
3. :func:`build_tracks` - the verified matches joined into tracks (connected components; one that
   sees an image twice is split into consistent tracks, not dropped).
4. :func:`choose_initial_pair` - many inliers and a wide enough triangulation angle.
5. :func:`initialize_pose` - the pair's relative pose from E with the cheirality test.
6. :func:`triangulate_initial` and :func:`refine_initial_points` - linear (DLT) then non-linear
   triangulation of the pair's tracks (H&Z chapter 12); like COLMAP, tracks seen in only two
   images are not triangulated (``ignore_two_view_tracks``).
7. :func:`reconstruct_incrementally` - a generator step: register the next image (linear PnP in
   RANSAC, then non-linear PnP; H&Z chapter 7), triangulate the tracks it completes, bundle adjust,
   and continue, complete and merge tracks as COLMAP's incremental triangulator does (section 4.5);
   it yields the growing reconstruction after every registration and the cost during adjustment.
8. :func:`filter_points` - drop observations with a large reprojection error and points with a
   small triangulation angle.
9. :func:`bundle_adjust_all` - the final bundle adjustment over all cameras and points (Triggs et
   al., "Bundle adjustment - a modern synthesis", 2000; H&Z appendix A6), optionally with K.

Every refinement reports its stage's reprojection error before and after (DLT vs non-linear
triangulation, linear vs non-linear PnP, before vs after bundle adjustment). With ground truth the
evaluations (:mod:`lab.modules.sfm.evaluate`) compare the cameras after a similarity alignment
(Umeyama 1991): rotation error in degrees and camera-centre error relative to the size of the
camera path. The math is split by topic: :mod:`~lab.modules.sfm.pairs`, :mod:`~lab.modules.sfm.tracks`,
:mod:`~lab.modules.sfm.model` (the growing model), :mod:`~lab.modules.sfm.registration` (the
incremental loop); the datasets are in :mod:`lab.modules.sfm.datasets`.

The model is typed: every stage from the two-view one on is a
:class:`~lab.data.reconstruction.SparseModel` (cameras, registered views, keypoints and tracks,
points with their colours and errors), one state name per stage; the pipeline exports the last one
(:data:`EXPORTS`: COLMAP text, transforms.json) and lists the names the viewer reads (:data:`VIEWS`).

State names (float64 unless said; V views, N keypoints, P points):
    images              ImageSet (V)      the photos (dataset)
    K                   (V, 3, 3)         camera matrix of each view (dataset)
    keypoints           Points2D          SIFT keypoints of every view (``view``), coloured from the images
    descriptors         (N, 128) float32  one descriptor per keypoint
    matches             (M, 4) int        ``(view a, view b, keypoint a, keypoint b)``, a < b, global keypoint
                                          indices
    inlier_matches      (M', 4) int       the matches consistent with their pair's F
    view_graph          (G, 5)            per verified pair: view a, view b, matches, inliers, median angle
                                          (deg)
    pair_poses          (G, 3, 4)         each verified pair's relative pose ``[R | t]`` (|t| = 1)
    track_of            (N,) int          the track of each keypoint (-1: none)
    initial_pair        (2,) int          the two views the reconstruction starts from
    initial_pose        (3, 4)            ``[R | t]`` of the second initial view (the first is the world
                                          frame)
    initial_model_dlt   SparseModel       the two-view model, points by linear triangulation
    initial_model       SparseModel       the two-view model, points by non-linear triangulation
    model               SparseModel       the incremental model (its ``track_of``: the tracks continued,
                                          completed and merged)
    filtered_model      SparseModel       after filtering
    adjusted_model      SparseModel       after the final bundle adjustment (its ``K`` refined when asked)
    cameras             Cameras           the registered cameras so far (``views``: their images)
    points3d            PointCloud        the points so far, coloured from the images
    observations        Points2D          every observation of a reconstructed point (``ids``: its point)
"""

from __future__ import annotations

from lab.core import Pipeline
from lab.data.reconstruction import SparseModel
from lab.modules.sfm.datasets import (FOCAL_GUESS_FACTOR, camera_path, check_intrinsics, exif_focal_px,
                                      match_files, matches_from_match_files, photos, read_k_matrix, rendered,
                                      scene_extent)
from lab.modules.sfm.evaluate import align_poses, evaluate_initial, evaluate_model, pose_errors, umeyama
from lab.modules.sfm.export import EXPORTED_MODEL, EXPORTS
from lab.modules.sfm.model import GrowingModel, error_colors
from lab.modules.sfm.pairs import image_pairs
from lab.modules.sfm.registration import RegistrationFailed
from lab.modules.sfm.steps import (PNP_MINIMUM, SIFT_OFFSET_PX, AdjustedModel, Features, FilteredModel,
                                   IncrementalModel, InitialModel, InitialPair, InitialPoints, InitialPose,
                                   PairMatches, Tracks, VerifiedPairs, build_tracks, bundle_adjust_all,
                                   choose_initial_pair, detect_all_features, filter_points, initialize_pose,
                                   match_all_pairs, reconstruct_incrementally, refine_initial_points,
                                   triangulate_initial, verify_pairs)
from lab.modules.sfm.tracks import complete_and_merge, keypoint_trees, split_inconsistent, unit_descriptors

#: The models of the stages, in pipeline order (one state name each).
MODEL_STAGES = ("initial_model_dlt", "initial_model", "model", "filtered_model", "adjusted_model")

#: State names the viewer's interactions (:mod:`lab.viewer.interactions.sfm`) read by name.
VIEWS = ("model", "filtered_model", "adjusted_model")

PIPELINE = Pipeline.build(
    name="sfm",
    title="Structure from motion",
    summary="Many photos in, cameras and a sparse point cloud out: features and matches for all pairs, "
            "geometric verification and the view graph, the initial pair and its pose from E, linear and "
            "non-linear triangulation, then register -> triangulate -> bundle adjust one image at a time, "
            "filtering and a final bundle adjustment.",
    steps=[detect_all_features, match_all_pairs, verify_pairs, build_tracks, choose_initial_pair,
           initialize_pose, triangulate_initial, refine_initial_points, reconstruct_incrementally,
           filter_points, bundle_adjust_all],
    datasets=[rendered, photos, match_files],
    evaluations={"initialize_pose": evaluate_initial,
                 "refine_initial_points": evaluate_model("initial_model"),
                 "reconstruct_incrementally": evaluate_model("model"),
                 "bundle_adjust_all": evaluate_model("adjusted_model")},
    exports=EXPORTS,
    views=VIEWS,
)

__all__ = [
    "EXPORTED_MODEL", "EXPORTS", "FOCAL_GUESS_FACTOR", "MODEL_STAGES", "PIPELINE", "PNP_MINIMUM",
    "SIFT_OFFSET_PX", "VIEWS", "AdjustedModel", "Features", "FilteredModel", "GrowingModel",
    "IncrementalModel", "InitialModel", "InitialPair", "InitialPoints", "InitialPose", "PairMatches",
    "RegistrationFailed", "SparseModel", "Tracks", "VerifiedPairs", "align_poses", "build_tracks",
    "bundle_adjust_all", "camera_path", "check_intrinsics", "choose_initial_pair", "complete_and_merge",
    "detect_all_features", "error_colors", "exif_focal_px", "filter_points", "image_pairs", "initialize_pose",
    "keypoint_trees", "match_all_pairs", "match_files", "matches_from_match_files", "photos", "pose_errors",
    "read_k_matrix", "reconstruct_incrementally", "refine_initial_points", "rendered", "scene_extent",
    "split_inconsistent", "triangulate_initial", "umeyama", "unit_descriptors", "verify_pairs",
]
