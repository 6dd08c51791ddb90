"""The steps of incremental structure from motion, in pipeline order (the package docstring lists the
state)."""

from __future__ import annotations

from collections.abc import Generator
from typing import Annotated, Any, Literal

import numpy as np

from lab.core import (Cameras, Curve, ImageSet, InvalidValue, PointCloud, Points2D, Progress, Range,
                      StepFailed, metric)
from lab.data.reconstruction import SparseModel
from lab.core.step import Warnings, step_result
from lab.geometry.camera import pixels_to_normalized
from lab.geometry.triangulation import (point_depths, projection_matrix, refine_points,
                                       reprojection_residuals, triangulate_dlt)
from lab.modules import epipolar
from lab.modules.sfm._checks import (check_images, check_keypoints, check_matches, check_model, check_pair,
                                    check_track_of, keypoint_views)
from lab.modules.sfm.datasets import check_intrinsics
from lab.modules.sfm.model import (GrowingModel, error_colors, freeze, observation_errors, poses_matrix,
                                   ray_angles_deg, refreeze, sample_colors)
from lab.modules.sfm.pairs import image_pairs, pair_parallax, pair_rows
from lab.modules.sfm.registration import (Adjustment, Incremental, Registration, TrackGrowth, Triangulation,
                                          bundle, weighted_rms)
from lab.modules.sfm.tracks import (connected_tracks, keypoint_trees, pair_observations, track_lengths,
                                    unit_descriptors_of)

#: Fewest 2D-3D correspondences the linear PnP (DLT) can use.
PNP_MINIMUM = 6

#: OpenCV's quarter-pixel SIFT bias, corrected at the source (:data:`lab.modules.epipolar.SIFT_OFFSET_PX`,
#: subtracted by ``epipolar.detect_features``); named here for reference only, not applied again.
SIFT_OFFSET_PX = epipolar.SIFT_OFFSET_PX

#: The robust losses of the bundle adjustments.
Loss = Literal["linear", "huber", "soft_l1", "cauchy", "arctan"]


# ----------------------------------------------------------------------------------------------------
# 1. Features and matches
# ----------------------------------------------------------------------------------------------------
@step_result
class Features:
    """Result of :func:`detect_all_features`."""

    keypoints: Points2D
    descriptors: np.ndarray
    warnings: Warnings
    keypoints_total: int = metric("keypoints in all images")
    keypoints_min: int = metric("fewest keypoints in one image")


def detect_all_features(images: ImageSet, *, max_features: Annotated[int, Range(0, 50000)] = 8192,
                        contrast_threshold: Annotated[float, Range(0.001, 0.5)] = 0.02) -> Features:
    """SIFT keypoints and descriptors in every image (the epipolar module's ``detect_features``).

    The two-view step runs on the images two at a time (an odd last image is paired with itself and
    its copy dropped); each keypoint gets the colour of its pixel. OpenCV's quarter-pixel bias is
    already removed there (:data:`lab.modules.epipolar.SIFT_OFFSET_PX`).

    Args:
        max_features: keep the strongest this many keypoints per image (0: all).
        contrast_threshold: reject weak extrema (OpenCV's contrastThreshold; lower finds more).

    Returns ``keypoints`` (Points2D, ``view`` per keypoint, image order) and ``descriptors``
    ``(N, 128)`` float32. Corresponds to ``cv2.SIFT_create().detectAndCompute`` per image.

    Reference: D. Lowe, IJCV 60(2), 2004; Schönberger and Frahm (2016), section 3.1.
    """
    images = check_images(images)
    xy, view, descriptors, colors, warnings = [], [], [], [], []
    for first in range(0, len(images), 2):
        second = min(first + 1, len(images) - 1)
        found = epipolar.detect_features(ImageSet((images[first], images[second])), max_features=max_features,
                                         contrast_threshold=contrast_threshold)
        found_view = keypoint_views(found.keypoints)
        for local, index in ((0, first), (1, second)):
            if local == 1 and second == first:
                continue
            keep = found_view == local
            points = found.keypoints.xy[keep]
            xy.append(points)
            view.append(np.full(len(points), index, dtype=np.int64))
            descriptors.append(found.descriptors[keep])
            colors.append(sample_colors(images[index], points))
            if len(points) < 50:
                warnings.append(f"{images.names[index]} (image {index}): only {len(points)} keypoints")
    counts = [len(p) for p in xy]
    keypoints = Points2D(np.concatenate(xy), view=np.concatenate(view), colors=np.concatenate(colors),
                         image="images")
    return Features(keypoints, np.concatenate(descriptors).astype(np.float32), tuple(warnings),
                    int(sum(counts)), int(min(counts)))


@step_result
class PairMatches:
    """Result of :func:`match_all_pairs`."""

    matches: np.ndarray
    pair_matches: Curve
    warnings: Warnings
    pairs: int = metric("image pairs matched")
    num_matches: int = metric("matches in all pairs")


def match_all_pairs(keypoints: Points2D, descriptors: np.ndarray, *,
                    ratio: Annotated[float, Range(0.05, 1.0)] = 0.8, mutual: bool = True,
                    pairs: Literal["exhaustive", "sequential"] = "exhaustive",
                    window: Annotated[int, Range(1, 30)] = 3) -> PairMatches:
    """Match the descriptors of every pair of images (the epipolar module's ``match_features``).

    Nearest neighbour, Lowe's ratio test and the mutual check, pair by pair.

    Args:
        ratio: largest allowed ratio of nearest to second-nearest distance.
        mutual: keep only matches that are each other's nearest neighbour.
        pairs: "exhaustive" (every pair, as COLMAP's exhaustive matcher) or "sequential" (each
            image with the next ``window`` ones, for video).
        window: how many following images "sequential" matches.

    Returns ``matches`` ``(M, 4)`` int rows ``(view a, view b, keypoint a, keypoint b)`` (global
    keypoint indices) and ``pair_matches``, a bar chart of the matches per pair. Corresponds to
    ``cv2.BFMatcher(cv2.NORM_L2).knnMatch`` per pair (pycolmap's ``match_exhaustive``).

    Reference: Lowe (2004), section 7.1; Schönberger and Frahm (2016), section 3.1.
    """
    views = int(keypoints.view.max()) + 1 if isinstance(keypoints, Points2D) and keypoints.view is not None \
        and len(keypoints) else 0
    keypoints = check_keypoints(keypoints)
    view = keypoint_views(keypoints)
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2 or len(descriptors) != len(keypoints):
        raise InvalidValue("descriptors", f"expected one row per keypoint ({len(keypoints)}), got "
                                          f"{descriptors.shape}")
    if views < 2:
        raise InvalidValue("keypoints",
                           f"structure from motion needs keypoints in at least two images, got {views}")
    index = [np.flatnonzero(view == v) for v in range(views)]
    rows, labels, counts, warnings = [], [], [], []
    for a, b in image_pairs(views, pairs=pairs, window=window):
        ia, ib = index[a], index[b]
        if len(ia) == 0 or len(ib) == 0:
            continue
        both = np.concatenate([ia, ib])
        local = Points2D(keypoints.xy[both], view=np.repeat([0, 1], [len(ia), len(ib)]))
        found = epipolar.match_features(local, descriptors[both], ratio=ratio, mutual=mutual)
        m = both[found.matches]
        rows.append(np.column_stack([np.full(len(m), a), np.full(len(m), b), m]).astype(np.int64))
        labels.append(f"{a}-{b}")
        counts.append(len(m))
    matches = np.concatenate(rows) if rows else np.zeros((0, 4), dtype=np.int64)
    if not len(matches):
        warnings.append("no matches between any two images")
    chart = Curve(np.arange(len(counts), dtype=np.float64),
                  np.asarray(counts, dtype=np.float64).reshape(1, -1),
                  kind="bar", title="Matches per image pair", xlabel="pair", ylabel="matches",
                  categories=tuple(labels))
    return PairMatches(matches, chart, tuple(warnings), len(counts), len(matches))


# ----------------------------------------------------------------------------------------------------
# 2. Geometric verification and the view graph
# ----------------------------------------------------------------------------------------------------
@step_result
class VerifiedPairs:
    """Result of :func:`verify_pairs`."""

    inlier_matches: np.ndarray
    view_graph: np.ndarray
    pair_poses: np.ndarray
    pair_inliers: Curve
    warnings: Warnings
    verified_pairs: int = metric("pairs whose matches an F explains")
    rejected_pairs: int = metric("pairs rejected (too few inliers, no F)")
    inliers: int = metric("inlier matches in all verified pairs")


def verify_pairs(images: ImageSet, keypoints: Points2D, matches: np.ndarray, K: np.ndarray, *,
                 threshold_px: Annotated[float, Range(0.1, 20.0)] = 1.5,
                 min_inliers: Annotated[int, Range(8, 10000)] = 20,
                 max_iterations: Annotated[int, Range(10, 100000)] = 2000,
                 rng: np.random.Generator) -> VerifiedPairs:
    """Geometric verification of every matched pair: F by RANSAC, then E and the relative pose (reused steps).

    For each pair: :func:`~lab.modules.epipolar.estimate_fundamental_ransac` (normalized 8-point
    algorithm inside LO-RANSAC, Sampson error), :func:`~lab.modules.epipolar.estimate_essential`
    (``E = K2^T F K1``) and :func:`~lab.modules.epipolar.recover_pose` (the candidate with the points
    in front of both cameras). A pair is kept when at least ``min_inliers`` matches fit F; it becomes
    an edge of the view graph with its inlier count and the median angle between the rays of its
    inliers (small for a pure rotation or a distant scene: no depth to triangulate).

    Args:
        threshold_px: largest Sampson error of an inlier, pixels.
        min_inliers: fewest inliers of a verified pair.
        max_iterations: most RANSAC samples per pair.

    Returns ``inlier_matches`` (the matches of ``matches`` that fit their pair's F), ``view_graph``
    ``(G, 5)`` rows ``(view a, view b, matches, inliers, median angle deg)``, ``pair_poses``
    ``(G, 3, 4)`` and a bar chart of inliers per pair. Warns about images left without a verified
    pair. Corresponds to COLMAP's two-view geometry verification (``pycolmap.verify_matches``).

    Reference: H&Z section 11.6 (algorithm 11.4) and section 9.6; Schönberger and Frahm (2016), section 3.1.
    """
    images = check_images(images)
    keypoints = check_keypoints(keypoints, len(images))
    matches = check_matches(matches, "matches", keypoints)
    K = check_intrinsics(K, images)
    keep = np.zeros(len(matches), dtype=bool)
    graph, poses, labels, warnings = [], [], [], []
    rejected = 0
    pair_keys = np.unique(matches[:, :2], axis=0) if len(matches) else np.zeros((0, 2), dtype=np.int64)
    for a, b in pair_keys:
        rows = pair_rows(matches, a, b)
        x1, x2 = keypoints.xy[matches[rows, 2]], keypoints.xy[matches[rows, 3]]
        if len(rows) < min_inliers:
            rejected += 1
            continue
        try:
            fit = epipolar.estimate_fundamental_ransac(x1, x2, threshold_px=threshold_px, confidence=0.999,
                                                       max_iterations=max_iterations, check_degenerate=False,
                                                       rng=rng)
            inliers = fit.inliers
            if inliers.sum() < min_inliers:
                raise epipolar.TooFewMatches("x1", f"{int(inliers.sum())} inliers")
            E = epipolar.estimate_essential(fit.F, ImageSet((images[a], images[b])), K[a], K[b])
            pose = epipolar.recover_pose(epipolar.decompose_essential(E), x1, x2, K[a], K[b], inliers)
        except (StepFailed, InvalidValue) as exc:
            rejected += 1
            warnings.append(f"pair {a}-{b} rejected: {exc.reason}")
            continue
        keep[rows[inliers]] = True
        angle = pair_parallax(x1[inliers], x2[inliers], K[a], K[b], pose[:, :3], pose[:, 3])
        graph.append([a, b, len(rows), int(inliers.sum()), angle])
        poses.append(pose)
        labels.append(f"{a}-{b}")
    view_graph = np.array(graph, dtype=np.float64).reshape(-1, 5)
    connected = set(view_graph[:, :2].astype(int).ravel().tolist())
    lonely = [f"{images.names[v]} (image {v})" for v in range(len(images)) if v not in connected]
    if lonely:
        warnings.append(f"no verified pair for {', '.join(lonely)}: they share no (consistent) matches with "
                        "any other image and cannot be registered")
    chart = Curve(np.arange(len(graph), dtype=np.float64), view_graph[:, 3].reshape(1, -1), kind="bar",
                  title="Inliers per verified pair", xlabel="pair", ylabel="inliers",
                  categories=tuple(labels))
    return VerifiedPairs(matches[keep], view_graph, np.array(poses).reshape(-1, 3, 4), chart, tuple(warnings),
                         len(graph), rejected, int(keep.sum()))


# ----------------------------------------------------------------------------------------------------
# 3. Tracks
# ----------------------------------------------------------------------------------------------------
@step_result
class Tracks:
    """Result of :func:`build_tracks`."""

    track_of: np.ndarray
    warnings: Warnings
    tracks: int = metric("tracks (points seen in two or more images)")
    mean_track_length: float = metric("images per track, on average")
    inconsistent_tracks: int = metric("components that saw one image twice (split into consistent tracks)")
    split_tracks: int = metric("consistent tracks kept from the inconsistent components")
    cut_matches: int = metric("matches cut to split the inconsistent components")
    dropped_keypoints: int = metric("keypoints of inconsistent components left in no track")


def build_tracks(keypoints: Points2D, inlier_matches: np.ndarray,
                 descriptors: np.ndarray | None = None) -> Tracks:
    """Join the verified matches into tracks: the connected components of the match graph, inconsistent ones
    split.

    Nodes are keypoints, edges the inlier matches; a component is one 3D point seen in several
    images (union-find, here ``scipy.sparse.csgraph.connected_components``). A component with two
    keypoints in one image is inconsistent (a wrong match somewhere); it is not dropped but split
    (:func:`~lab.modules.sfm.split_inconsistent`): its edges are re-joined best first (smallest
    descriptor distance when ``descriptors`` are given) and an edge that would make a track see one
    image twice is cut, so the consistent part of the component is kept.

    Returns ``track_of`` ``(N,)`` int, the track of each keypoint (-1: none), tracks numbered 0 ..

    Reference: Schönberger and Frahm (2016), sections 3.1 (scene graph) and 4.5 (a track sees an
    image once); Snavely et al., "Photo tourism" (2006), section 4.1.
    """
    keypoints = check_keypoints(keypoints)
    m = check_matches(inlier_matches, "inlier_matches", keypoints)
    if not len(m):
        return Tracks(np.full(len(keypoints), -1, dtype=np.int64), ("no verified matches: no tracks",), 0,
                      0.0, 0, 0, 0, 0)
    track_of, count, (inconsistent, split, cut, dropped) = connected_tracks(
        keypoints, m, unit_descriptors_of(descriptors, keypoints))
    mean = float(np.sum(track_of >= 0) / count) if count else 0.0
    warnings = () if count else ("no consistent tracks",)
    return Tracks(track_of, warnings, count, mean, inconsistent, split, cut, dropped)


# ----------------------------------------------------------------------------------------------------
# 4. The initial pair and its pose
# ----------------------------------------------------------------------------------------------------
@step_result
class InitialPair:
    """Result of :func:`choose_initial_pair`."""

    initial_pair: np.ndarray
    pair_inliers: int = metric("inliers of the chosen pair")
    pair_angle_deg: float = metric("median triangulation angle of the chosen pair", unit="deg")


def choose_initial_pair(view_graph: np.ndarray, *, min_angle_deg: Annotated[float, Range(0.0, 60.0)] = 4.0,
                        min_inliers: Annotated[int, Range(8, 100000)] = 50) -> InitialPair:
    """The pair to start from: the most inliers among pairs whose median triangulation angle is wide enough.

    Many inliers make the two-view model reliable; a wide angle makes its depths well determined
    (a pair with a small angle, e.g. a pure rotation, cannot be triangulated). Among the pairs with
    ``median angle >= min_angle_deg`` and ``inliers >= min_inliers`` the one with most inliers;
    if none qualifies, the pair with the largest ``inliers x angle``.

    Args:
        min_angle_deg: smallest median triangulation angle of the initial pair.
        min_inliers: fewest inliers of the initial pair.

    Returns ``initial_pair`` ``(2,)`` int. Raises when the view graph is empty.

    Reference: Schönberger and Frahm (2016), section 4.2 (initialization).
    """
    graph = np.asarray(view_graph, dtype=np.float64)
    if graph.ndim != 2 or graph.shape[1] != 5:
        raise InvalidValue("view_graph", f"expected (G, 5) rows, got {graph.shape}")
    if not len(graph):
        raise InvalidValue("view_graph", "no verified image pair: the images share no consistent matches, so "
                                         "nothing can be reconstructed")
    good = (graph[:, 4] >= min_angle_deg) & (graph[:, 3] >= min_inliers)
    if good.any():
        best = int(np.argmax(np.where(good, graph[:, 3], -1.0)))
    else:
        best = int(np.argmax(graph[:, 3] * graph[:, 4]))
    return InitialPair(graph[best, :2].astype(np.int64), int(graph[best, 3]), float(graph[best, 4]))


@step_result
class InitialPose:
    """Result of :func:`initialize_pose`."""

    initial_pose: np.ndarray
    warnings: Warnings
    inliers: int = metric("matches of the pair consistent with F")
    in_front: int = metric("inliers in front of both cameras (cheirality)")
    sampson_rms_px: float = metric("RMS Sampson distance of the inliers to E(R, t)", unit="px")
    median_parallax_deg: float = metric("median angle between the two rays of an inlier", unit="deg")


def initialize_pose(images: ImageSet, keypoints: Points2D, inlier_matches: np.ndarray, K: np.ndarray,
                    initial_pair: np.ndarray, *, threshold_px: Annotated[float, Range(0.1, 20.0)] = 1.5,
                    rng: np.random.Generator) -> InitialPose:
    """The relative pose of the initial pair from E, with the cheirality test (the epipolar steps, reused).

    F by RANSAC on the pair's verified matches, ``E = K2^T F K1`` projected onto the essential
    matrices, its four ``[R | t]`` (:func:`~lab.modules.epipolar.decompose_essential`), the one
    with the points in front of both cameras (:func:`~lab.modules.epipolar.recover_pose`), then
    polished on the Sampson error (:func:`~lab.modules.epipolar.refine_pose`). The first view of
    the pair is the world frame; ``|t| = 1`` fixes the unknown scale.

    Args:
        threshold_px: largest Sampson error of an inlier, pixels.

    Returns ``initial_pose`` ``(3, 4)`` = ``[R | t]`` of the second view.

    Reference: H&Z sections 9.6.2-9.6.3 (result 9.19, figure 9.12); Schönberger and Frahm (2016), section 4.2.
    """
    images = check_images(images)
    keypoints = check_keypoints(keypoints, len(images))
    m = check_matches(inlier_matches, "inlier_matches", keypoints)
    K = check_intrinsics(K, images)
    a, b = check_pair(initial_pair, len(images))
    rows = pair_rows(m, min(a, b), max(a, b))
    if len(rows) < epipolar.SAMPLE_SIZE:
        raise InvalidValue("initial_pair", f"images {a} and {b} share only {len(rows)} verified matches")
    first, second = (2, 3) if a < b else (3, 2)
    x1, x2 = keypoints.xy[m[rows, first]], keypoints.xy[m[rows, second]]
    fit = epipolar.estimate_fundamental_ransac(x1, x2, threshold_px=threshold_px, confidence=0.999,
                                               check_degenerate=False, rng=rng)
    E = epipolar.estimate_essential(fit.F, ImageSet((images[a], images[b])), K[a], K[b])
    candidates = epipolar.decompose_essential(E)
    pose = epipolar.recover_pose(candidates, x1, x2, K[a], K[b], fit.inliers)
    counts = epipolar.cheirality_counts(candidates, pixels_to_normalized(x1[fit.inliers], K[a]),
                                        pixels_to_normalized(x2[fit.inliers], K[b]))
    refined = epipolar.refine_pose(pose, x1, x2, K[a], K[b], fit.inliers)
    return InitialPose(poses_matrix(refined.R, refined.t), refined.warnings, int(fit.inliers.sum()),
                       int(counts.max()), refined.sampson_rms_px, refined.median_parallax_deg)


# ----------------------------------------------------------------------------------------------------
# 5. Triangulating the initial pair: linear, then non-linear
# ----------------------------------------------------------------------------------------------------
@step_result
class InitialPoints:
    """Result of :func:`triangulate_initial`."""

    initial_model_dlt: SparseModel
    warnings: Warnings
    points: int = metric("points kept")
    dropped_behind: int = metric("points behind a camera, dropped")
    dropped_angle: int = metric("points with a too small triangulation angle, dropped")
    reprojection_rms_px: float = metric("RMS reprojection error of the DLT points", unit="px")
    ignored_two_view: int = metric("tracks seen by the two initial images only, not triangulated")


def triangulate_initial(images: ImageSet, keypoints: Points2D, track_of: np.ndarray, K: np.ndarray,
                        initial_pair: np.ndarray, initial_pose: np.ndarray, *,
                        min_angle_deg: Annotated[float, Range(0.0, 30.0)] = 1.0,
                        ignore_two_view_tracks: bool = True) -> InitialPoints:
    """Linear (DLT) triangulation of the tracks seen in both initial views (``triangulate_dlt``): the two-view
    model.

    ``P1 = K1 [I | 0]``, ``P2 = K2 [R | t]``; each point is the null vector of its ``4 x 4`` DLT
    system. Points behind either camera (cheirality) or whose two rays meet at less than
    ``min_angle_deg`` (badly conditioned depth) are dropped. A track with no keypoint beyond the
    two images (a two-view track) is skipped when ``ignore_two_view_tracks``, as COLMAP's
    triangulator does by default: its point could never be checked by a third view nor help
    register one.

    Args:
        min_angle_deg: smallest angle between a point's two rays.
        ignore_two_view_tracks: do not triangulate tracks of two keypoints (COLMAP's
            ``ignore_two_view_tracks``, on by default there too).

    Returns ``initial_model_dlt``, the :class:`~lab.data.reconstruction.SparseModel` of the two
    views (the first at the origin, the second at ``initial_pose``) and the DLT points, on the tracks
    of ``build_tracks``. Corresponds to ``cv2.triangulatePoints(P1, P2, x1.T, x2.T)``.

    Reference: H&Z section 12.2.
    """
    images = check_images(images)
    keypoints = check_keypoints(keypoints, len(images))
    track_of = check_track_of(track_of, keypoints)
    K = check_intrinsics(K, images)
    a, b = check_pair(initial_pair, len(images))
    pose = np.asarray(initial_pose, dtype=np.float64).reshape(3, 4)
    tracks, ka, kb = pair_observations(keypoints, track_of, a, b)
    ignored = 0
    if ignore_two_view_tracks:
        longer = track_lengths(track_of)[tracks] > 2
        ignored = int(np.sum(~longer))
        tracks, ka, kb = tracks[longer], ka[longer], kb[longer]
    if len(tracks) < PNP_MINIMUM:
        raise InvalidValue("track_of",
                           f"images {a} and {b} share only {len(tracks)} tracks: choose another pair")
    P = np.stack([projection_matrix(K[a], np.eye(3), np.zeros(3)),
                  projection_matrix(K[b], pose[:, :3], pose[:, 3])])
    x = np.stack([keypoints.xy[ka], keypoints.xy[kb]])
    X = triangulate_dlt(P, x)
    finite = np.all(np.isfinite(X), axis=1)
    X = np.where(finite[:, None], X, 0.0)
    front = finite & np.all(point_depths(P, X) > 0, axis=0)
    centers = np.stack([np.zeros(3), -pose[:, :3].T @ pose[:, 3]])
    angle = ray_angles_deg(centers, X, np.ones((2, len(X)), dtype=bool))
    wide = angle >= min_angle_deg
    keep = front & wide
    residual = reprojection_residuals(P, X[keep], x[:, keep])
    rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=2)))) if keep.any() else 0.0
    warnings = () if keep.sum() >= 50 else (f"only {int(keep.sum())} points from the initial pair",)
    poses = np.zeros((len(images), 3, 4))
    poses[a] = poses_matrix(np.eye(3), np.zeros(3))
    poses[b] = pose
    registered = np.zeros(len(images), dtype=bool)
    registered[[a, b]] = True
    two_view = GrowingModel(poses, registered, X[keep], tracks[keep], np.ones(len(keypoints), dtype=bool))
    sizes = np.array([[image.width, image.height] for image in images.images])
    return InitialPoints(freeze(two_view, track_of, K, keypoints, images.names, sizes), warnings,
                         int(keep.sum()), int(np.sum(~front)), int(np.sum(front & ~wide)), rms, ignored)


@step_result
class InitialModel:
    """Result of :func:`refine_initial_points`."""

    initial_model: SparseModel
    cameras: Cameras
    points3d: PointCloud
    triangulation_cost: Curve
    reprojection_rms_dlt_px: float = metric("RMS reprojection error of the DLT points (linear)", unit="px")
    reprojection_rms_px: float = metric("RMS reprojection error after non-linear triangulation", unit="px")
    points: int = metric("points of the two-view model")


def refine_initial_points(initial_model_dlt: SparseModel, initial_pair: np.ndarray, *,
                          iterations: Annotated[int, Range(0, 100)] = 10) -> InitialModel:
    """Non-linear triangulation: move each point to minimize its reprojection error in both views (cameras
    fixed).

    Levenberg-Marquardt per point on ``|pi(P1 X) - x1|^2 + |pi(P2 X) - x2|^2``
    (:func:`lab.geometry.triangulation.refine_points`), the maximum-likelihood point under
    Gaussian pixel noise where the DLT minimized an algebraic error.

    Args:
        iterations: most Levenberg-Marquardt iterations (0: keep the DLT points).

    Returns ``initial_model``, the two-view model with the refined points, ``cameras``,
    ``points3d`` and the RMS per iteration. No single OpenCV call.

    Reference: H&Z section 12.5 (the maximum-likelihood criterion) and appendix A6.2.
    """
    dlt = check_model(initial_model_dlt, "initial_model_dlt")
    a, b = check_pair(initial_pair, len(dlt))
    if not len(dlt.points):
        raise InvalidValue("initial_model_dlt", "no points to refine")
    kp, views, point = dlt.observations()
    ka, kb = np.zeros(len(dlt.points), dtype=np.int64), np.zeros(len(dlt.points), dtype=np.int64)
    ka[point[views == a]], kb[point[views == b]] = kp[views == a], kp[views == b]
    K, pose = dlt.K, dlt.poses[b]
    P = np.stack([projection_matrix(K[a], np.eye(3), np.zeros(3)),
                  projection_matrix(K[b], pose[:, :3], pose[:, 3])])
    X, history = refine_points(P, np.stack([dlt.keypoints.xy[ka], dlt.keypoints.xy[kb]]), dlt.points,
                               iterations=int(iterations))
    refined = GrowingModel.of(dlt)
    refined.points = X
    model = refreeze(refined, dlt.track_of, dlt)
    cost = Curve(np.arange(len(history), dtype=np.float64), history, title="Non-linear triangulation",
                 xlabel="iteration", ylabel="RMS reprojection error (px)", labels=("RMS",))
    return InitialModel(model, model.cameras(image="images"), model.point_cloud(), cost, float(history[0]),
                        float(history[-1]), len(X))


# ----------------------------------------------------------------------------------------------------
# 6. The incremental loop: register, triangulate, bundle adjust
# ----------------------------------------------------------------------------------------------------
@step_result
class IncrementalModel:
    """Result of :func:`reconstruct_incrementally`."""

    model: SparseModel
    cameras: Cameras
    points3d: PointCloud
    observations: Points2D
    registration_errors: Curve
    warnings: Warnings
    registered_images: int = metric("images registered (initial pair included)")
    points_total: int = metric("3D points")
    mean_track_length: float = metric("observations per point, on average")
    observations_continued: int = metric("observations of existing points added by the registered images "
                                         "(track continuation)")
    observations_completed: int = metric("observations attached to existing points by track completion")
    tracks_merged: int = metric("pairs of points merged into one (track merging)")
    pnp_rms_linear_px: float = metric("RMS reprojection error of the PnP inliers, linear PnP (DLT in "
                                      "RANSAC), mean over registrations", unit="px")
    pnp_rms_nonlinear_px: float = metric("the same after non-linear PnP", unit="px")
    triangulation_rms_linear_px: float = metric("RMS reprojection error of the new points, DLT", unit="px")
    triangulation_rms_nonlinear_px: float = metric("the same after non-linear triangulation", unit="px")
    ba_rms_before_px: float = metric("RMS reprojection error before the last bundle adjustment", unit="px")
    ba_rms_after_px: float = metric("RMS reprojection error after the last bundle adjustment", unit="px")
    ba_never_raised: bool = metric("no bundle adjustment raised the RMS error")


def reconstruct_incrementally(initial_model: SparseModel, initial_pair: np.ndarray,
                              descriptors: np.ndarray | None = None, *,
                              pnp_threshold_px: Annotated[float, Range(0.5, 50.0)] = 4.0,
                              min_correspondences: Annotated[int, Range(6, 10000)] = 20,
                              min_angle_deg: Annotated[float, Range(0.0, 30.0)] = 1.5,
                              max_error_px: Annotated[float, Range(0.5, 50.0)] = 4.0,
                              ba_loss: Loss = "huber",
                              ba_iterations: Annotated[int, Range(0, 200)] = 5,
                              ba_growth: Annotated[float, Range(1.0, 10.0)] = 1.25,
                              complete_tracks: bool = True,
                              ignore_two_view_tracks: bool = True,
                              complete_max_error_px: Annotated[float, Range(0.1, 50.0)] = 2.0,
                              max_descriptor_distance: Annotated[float, Range(0.0, 2.0)] = 0.5,
                              rng: np.random.Generator,
                              ) -> Generator[Progress, None, IncrementalModel]:
    """Grow the two-view model one image at a time: register -> triangulate -> bundle adjust (a generator
    step).

    Repeat while an unregistered image sees at least ``min_correspondences`` reconstructed points
    (through its tracks), taking the one that sees most (Schönberger and Frahm 2016, section 4.2,
    "next best view"):

    1. **Register** it: linear PnP (DLT on 6-point samples, rotation orthonormalised with det +1)
       inside RANSAC (:func:`lab.geometry.pnp.pnp_ransac`, H&Z section 7.1), then non-linear PnP
       (:func:`lab.geometry.pnp.refine_pnp`, H&Z section 7.2) on the inliers; outlier observations
       of the image are no longer used.
    2. **Triangulate** every track that now has two or more registered observations and no point
       (DLT over all its views, then Levenberg-Marquardt per point; H&Z sections 12.2 and 12.5), kept
       when in front of its cameras, with a triangulation angle of at least ``min_angle_deg`` and
       every reprojection error below ``max_error_px``.
    3. **Bundle adjust**, when the model has grown by ``ba_growth`` since the last time, all
       registered cameras and points (:func:`lab.geometry.bundle_adjustment.bundle_adjust`, the
       first initial view and the scale held; Triggs et al. 2000), then stop using observations
       whose error exceeds ``max_error_px``.
    4. **Grow the tracks** as COLMAP's incremental triangulator does (section 4.5; the module
       docstring of :mod:`lab.modules.sfm.tracks`): *create* only points of three or more images
       when ``ignore_two_view_tracks`` (a two-view track is triangulated on trial and kept only if
       completion finds it in a third image); *continue* (a keypoint of the new image whose track
       has a point becomes an observation if it reprojects within ``complete_max_error_px``);
       *complete* (a point projected into a registered image its track does not see takes the
       nearest keypoint within ``complete_max_error_px`` whose descriptor is within
       ``max_descriptor_distance`` of the point's: the guided search of H&Z algorithm 11.4 step v);
       *merge* (two points whose tracks see no image in common and whose observations all
       reproject within ``complete_max_error_px`` of their weighted mean become one). Completion
       and merging run after every registration and once more at the end.

    Yields :class:`~lab.core.Progress` after each registration (``values``: the cameras and points
    so far) and at every bundle-adjustment iteration (``loss``: RMS reprojection error, px).

    Args:
        pnp_threshold_px: RANSAC inlier threshold of the PnP reprojection error, pixels.
        min_correspondences: fewest 2D-3D correspondences (and PnP inliers) to register an image.
        min_angle_deg: smallest triangulation angle of a new point.
        max_error_px: largest reprojection error of an observation kept.
        ba_loss: robust loss of the bundle adjustments.
        ba_iterations: most iterations of each bundle adjustment (0: none inside the loop).
        ba_growth: adjust when the number of registered images has grown by this factor since the
            last adjustment (1: after every registration; COLMAP's ``ba_global_frames_ratio``).
        complete_tracks: continue, complete and merge tracks (off: the tracks of ``build_tracks`` only).
        complete_max_error_px: largest reprojection error of an observation added by continuation,
            completion or merging (COLMAP's ``complete_max_reproj_error`` is 4 px; 2 here, as
            :func:`filter_points` keeps 1 px).
        ignore_two_view_tracks: do not triangulate tracks of two keypoints (COLMAP's option of that
            name, on by default): such a point is never checked by a third image.
        max_descriptor_distance: largest distance between unit SIFT descriptors of a keypoint added
            by completion and the point's observations (COLMAP's matcher allows 0.7; candidates
            here skip the ratio test, and on the 12-view benchmark orbit 0.6-0.7 let in
            observations that raised the rotation error, 0.5 did not).

    Returns ``model``, the grown :class:`~lab.data.reconstruction.SparseModel` (its ``track_of``:
    the tracks after continuation, completion and merging; the state's ``track_of`` stays
    ``build_tracks``'), ``cameras``, ``points3d``, ``observations`` and ``registration_errors`` (per
    registered image: the linear and non-linear PnP RMS). Warns with each image that could not be
    registered and why. Corresponds to ``pycolmap.incremental_mapping``.

    Reference: Schönberger and Frahm, CVPR 2016, sections 3-4; H&Z chapters 7 and 12; Triggs et al. (2000).
    """
    start = check_model(initial_model, "initial_model")
    keypoints = start.keypoints
    tracks = start.track_of.copy()  # the tracks grow: continued, completed, merged
    anchor, _ = check_pair(initial_pair, len(start))
    loop = Incremental(
        GrowingModel.of(start), start.K, keypoints, tracks, unit_descriptors_of(descriptors, keypoints),
        start.names,
        start.sizes.astype(np.float64), anchor, Registration(pnp_threshold_px, min_correspondences),
        Triangulation(min_angle_deg, max_error_px, 2 if complete_tracks or not ignore_two_view_tracks else 3),
        Adjustment(ba_loss, ba_iterations, ba_growth),
        TrackGrowth(complete_tracks, ignore_two_view_tracks, complete_max_error_px, max_descriptor_distance),
        keypoint_trees(keypoints, len(start)) if complete_tracks else {})

    def preview() -> dict[str, Any]:
        now = refreeze(loop.model, tracks, start)
        return {"cameras": now.cameras(image="images"), "points3d": now.point_cloud()}

    yield from loop.run(rng, preview)
    model = refreeze(loop.model, tracks, start)
    _, _, point = model.observations()
    counts = np.bincount(point, minlength=len(model.points)) if len(point) else np.zeros(0)
    return IncrementalModel(
        model, model.cameras(image="images"), model.point_cloud(), model.observation_pixels(image="images"),
        loop.registration_chart(), loop.warnings(), registered_images=int(model.registered.sum()),
        points_total=len(model.points), mean_track_length=float(counts.mean()) if len(counts) else 0.0,
        observations_continued=loop.continued, observations_completed=loop.completed,
        tracks_merged=loop.merged,
        pnp_rms_linear_px=float(np.mean(loop.linear_rms)) if loop.linear_rms else 0.0,
        pnp_rms_nonlinear_px=float(np.mean(loop.nonlinear_rms)) if loop.nonlinear_rms else 0.0,
        triangulation_rms_linear_px=weighted_rms(loop.tri_before),
        triangulation_rms_nonlinear_px=weighted_rms(loop.tri_after),
        ba_rms_before_px=loop.ba_before[-1] if loop.ba_before else 0.0,
        ba_rms_after_px=loop.ba_after[-1] if loop.ba_after else 0.0, ba_never_raised=bool(loop.ba_ok))


# ----------------------------------------------------------------------------------------------------
# 7. Filtering
# ----------------------------------------------------------------------------------------------------
@step_result
class FilteredModel:
    """Result of :func:`filter_points`."""

    filtered_model: SparseModel
    points3d: PointCloud
    observations: Points2D
    removed_observations: int = metric("observations removed (reprojection error too large)")
    removed_points: int = metric("points removed (fewer than two observations left, or too small an angle)")
    points_total: int = metric("points kept")


def filter_points(model: SparseModel, *, max_error_px: Annotated[float, Range(0.1, 50.0)] = 1.0,
                  min_angle_deg: Annotated[float, Range(0.0, 30.0)] = 1.5) -> FilteredModel:
    """Drop observations whose reprojection error exceeds ``max_error_px``, then points left with fewer
    than two observations or whose largest triangulation angle is below ``min_angle_deg``.

    Run before the final bundle adjustment, so that it fits clean observations. The default 1 px
    suits calibrated cameras and SIFT (errors of a few tenths of a pixel); with a guessed K, raise it
    (COLMAP's default is 4 px).

    Args:
        max_error_px: largest reprojection error of an observation kept, pixels.
        min_angle_deg: smallest largest-angle between two rays of a point kept, degrees.

    Returns ``filtered_model``: the model without those observations and points. Corresponds to
    COLMAP's ``FilterPoints`` (max reprojection error, min triangulation angle).

    Reference: Schönberger and Frahm (2016), section 4.5 (filtering).
    """
    model = check_model(model, "model")
    keypoints, track_of, K = model.keypoints, model.track_of, model.K
    kept = GrowingModel.of(model)
    kp, views, point = kept.observations(keypoints, track_of)
    errors = observation_errors(kept, K, keypoints, kp, views, point)
    bad = errors > max_error_px
    kept.observed[kp[bad]] = False
    views, point = views[~bad], point[~bad]
    counts = np.bincount(point, minlength=len(kept.points))
    centers = -np.einsum("vji,vj->vi", kept.poses[:, :, :3], kept.poses[:, :, 3])
    mask = np.zeros((len(model), len(kept.points)), dtype=bool)
    mask[views, point] = True
    angles = ray_angles_deg(centers, kept.points, mask) if len(kept.points) else np.zeros(0)
    keep = (counts >= 2) & (angles >= min_angle_deg)
    kept.points, kept.point_tracks = kept.points[keep], kept.point_tracks[keep]
    if not len(kept.points):
        raise StepFailed("filter_points",
                         f"no point has two observations within {max_error_px:g} px and an angle "
                         f"of {min_angle_deg:g} degrees; loosen the limits")
    filtered = refreeze(kept, track_of, model)
    return FilteredModel(filtered, filtered.point_cloud(), filtered.observation_pixels(image="images"),
                         int(bad.sum()), len(model.points) - int(keep.sum()), len(filtered.points))


# ----------------------------------------------------------------------------------------------------
# 8. Final bundle adjustment
# ----------------------------------------------------------------------------------------------------
@step_result
class AdjustedModel:
    """Result of :func:`bundle_adjust_all`."""

    adjusted_model: SparseModel
    cameras: Cameras
    points3d: PointCloud
    observations: Points2D
    ba_cost: Curve
    rms_before_px: float = metric("RMS reprojection error before bundle adjustment", unit="px")
    rms_after_px: float = metric("RMS reprojection error after bundle adjustment", unit="px")
    iterations: int = metric("trust-region iterations")
    improved: bool = metric("the adjustment lowered the error (else the input is kept)")
    registered_images: int = metric("registered images")
    points_total: int = metric("3D points")
    mean_track_length: float = metric("observations per point, on average")
    reprojection_mean_px: float = metric("mean reprojection error over all observations", unit="px")


def bundle_adjust_all(filtered_model: SparseModel, initial_pair: np.ndarray, *, loss: Loss = "huber",
                      f_scale: Annotated[float, Range(0.01, 100.0)] = 1.0, refine_intrinsics: bool = False,
                      max_iterations: Annotated[int, Range(1, 500)] = 50,
                      ) -> Generator[Progress, None, AdjustedModel]:
    """The final bundle adjustment: all registered cameras and filtered points together, optionally K.

    Minimizes ``sum rho(|pi(K_c (R_c X_p + t_c)) - x|^2)`` over every camera pose (axis-angle and
    translation) and point, with the sparse Jacobian structure given to
    ``scipy.optimize.least_squares`` (trust-region reflective, LSMR; robust ``loss`` with inlier
    scale ``f_scale`` px) (:func:`lab.geometry.bundle_adjustment.bundle_adjust`). The first initial
    view is held fixed and one translation entry fixes the scale (the gauge). The result is kept
    only if the RMS error falls (never a worse model). Yields the RMS at every iteration.

    Args:
        loss: robust loss ("linear" is plain least squares).
        f_scale: residual size (px) beyond which the robust loss down-weights.
        refine_intrinsics: also refine fx, fy, cx, cy (one K when all views share it).
        max_iterations: most trust-region iterations.

    Returns ``adjusted_model`` (its ``errors``: each point's mean reprojection error), ``cameras``
    tinted by their mean error (green 0 px to red 2 px), ``points3d``, ``observations`` and
    ``ba_cost`` (RMS per iteration). Corresponds to ``pycolmap.bundle_adjustment`` (Ceres).

    Reference: Triggs, McLauchlan, Hartley and Fitzgibbon, "Bundle adjustment - a modern synthesis"
    (2000); H&Z appendix A6.3; Schönberger and Frahm (2016), section 4.5.
    """
    filtered = check_model(filtered_model, "filtered_model")
    keypoints, track_of, K = filtered.keypoints, filtered.track_of, filtered.K
    anchor, _ = check_pair(initial_pair, len(filtered))
    model = GrowingModel.of(filtered)
    if not model.registered[anchor]:
        anchor = int(np.flatnonzero(model.registered)[0])
    adjusting = bundle(model, K, keypoints, track_of, anchor, loss=loss, f_scale=f_scale,
                       max_iterations=max_iterations, refine_intrinsics=refine_intrinsics)
    while True:
        try:
            iteration, rms = next(adjusting)
        except StopIteration as stop:
            result, cams, K_sub = stop.value
            break
        yield Progress(iteration, max_iterations, rms, "bundle adjustment")
    K_out = K.copy()
    K_out[cams] = K_sub
    kp, views, point = model.observations(keypoints, track_of)
    errors = observation_errors(model, K_out, keypoints, kp, views, point)
    counts = np.bincount(point, minlength=len(model.points))
    per_camera = np.array([errors[views == v].mean() if np.any(views == v) else 0.0
                           for v in np.flatnonzero(model.registered)])
    adjusted = refreeze(model, track_of, filtered, K_out)
    history = np.asarray(result.cost_history, dtype=np.float64)
    cost = Curve(np.arange(len(history), dtype=np.float64), history, title="Bundle adjustment",
                 xlabel="iteration", ylabel="RMS reprojection error (px)", labels=("RMS",))
    return AdjustedModel(adjusted, adjusted.cameras(image="images", colors=error_colors(per_camera, 2.0)),
                         adjusted.point_cloud(), adjusted.observation_pixels(image="images"), cost,
                         result.rms_before, result.rms_after, int(result.iterations), bool(result.improved),
                         int(model.registered.sum()), len(model.points), float(counts.mean()),
                         float(errors.mean()) if len(errors) else 0.0)
