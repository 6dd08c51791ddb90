"""Incremental structure from motion: many photos in, cameras and a sparse point cloud out, one image at a time.

The classical incremental pipeline (Schönberger and Frahm, "Structure-from-Motion Revisited", CVPR
2016, the COLMAP paper, section 3), as steps:

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
evaluations compare the cameras after a similarity alignment (Umeyama 1991): rotation error in
degrees and camera-centre error relative to the size of the camera path.

State names (float64 unless said; V views, N keypoints, T tracks, P points):
    images              ImageSet (V)      the photos (dataset)
    K                   (V, 3, 3)         camera matrix of each view (dataset)
    keypoints           Points2D          SIFT keypoints of every view (``view``), coloured from the images
    descriptors         (N, 128) float32  one descriptor per keypoint
    matches             (M, 4) int        ``(view a, view b, keypoint a, keypoint b)``, a < b, global keypoint indices
    inlier_matches      (M', 4) int       the matches consistent with their pair's F
    view_graph          (G, 5)            per verified pair: view a, view b, matches, inliers, median angle (deg)
    pair_poses          (G, 3, 4)         each verified pair's relative pose ``[R | t]`` (|t| = 1)
    track_of            (N,) int          the track of each keypoint (-1: none)
    initial_pair        (2,) int          the two views the reconstruction starts from
    initial_pose        (3, 4)            ``[R | t]`` of the second initial view (the first is the world frame)
    initial_points_dlt  (P, 3)            linear triangulation of the pair's tracks; initial_point_tracks (P,) int
    initial_*           the two-view model: poses (V, 3, 4), registered (V,) bool, points (P, 3), point_tracks (P,)
    poses, registered, points, point_tracks, observed
                        the incremental model; ``observed`` (N,) bool: keypoints still used as observations
    model_track_of      (N,) int          the track of each keypoint after the incremental step continued,
                                          completed and merged tracks (``point_tracks`` and later steps use it)
    filtered_points, filtered_point_tracks, filtered_observed   after filtering
    adjusted_poses, adjusted_K, adjusted_points, point_errors     after the final bundle adjustment
    cameras             Cameras           the registered cameras so far (``views``: their images)
    points3d            PointCloud        the points so far, coloured from the images
    observations        Points2D          every observation of a reconstructed point (``ids``: its point)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Generator, Literal

import numpy as np

from lab.core.step import step_result, Warnings
from lab.core import (Cameras, Curve, ImageSet, InvalidValue, Pipeline, PointCloud, Points2D, Progress, Range,
                      StepFailed, metric)
from lab.data.multiview import check_intrinsics, match_files, photos, rendered
from lab.geometry.bundle_adjustment import bundle_adjust_progress
from lab.geometry.camera import pixels_to_normalized
from lab.geometry.pnp import pnp_ransac, refine_pnp, reprojection_errors
from lab.geometry.rotations import nearest_rotation, rotation_angle_deg
from lab.geometry.triangulation import point_depths, projection_matrix, refine_points, triangulate_dlt
from lab.modules import epipolar

#: Fewest 2D-3D correspondences the linear PnP (DLT) can use.
PNP_MINIMUM = 6

#: OpenCV's quarter-pixel SIFT bias, corrected at the source (:data:`lab.modules.epipolar.SIFT_OFFSET_PX`,
#: subtracted by ``epipolar.detect_features``); named here for reference only, not applied again.
SIFT_OFFSET_PX = epipolar.SIFT_OFFSET_PX


class RegistrationFailed(StepFailed):
    """No image beyond the initial pair could be registered."""


# ----------------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------------
def _images(images: Any) -> ImageSet:
    if not isinstance(images, ImageSet):
        raise InvalidValue("images", f"expected an ImageSet, got {type(images).__name__}")
    if len(images) < 2:
        raise InvalidValue("images", f"structure from motion needs at least two images, got {len(images)}")
    return images


def _keypoints(keypoints: Any, views: int | None = None) -> Points2D:
    if not isinstance(keypoints, Points2D) or keypoints.view is None:
        raise InvalidValue("keypoints", "expected Points2D with a view per keypoint")
    if views is not None and len(keypoints) and (keypoints.view.min() < 0 or keypoints.view.max() >= views):
        raise InvalidValue("keypoints", f"keypoint views must lie in [0, {views})")
    return keypoints


def _matches(value: Any, name: str, keypoints: Points2D) -> np.ndarray:
    m = np.asarray(value)
    if m.ndim != 2 or m.shape[1] != 4 or (len(m) and not np.issubdtype(m.dtype, np.integer)):
        raise InvalidValue(name, f"expected (M, 4) integer rows (view a, view b, keypoint a, keypoint b), got "
                                 f"{m.shape} {m.dtype}")
    m = m.astype(np.int64)
    if len(m) and (m[:, 2:].min() < 0 or m[:, 2:].max() >= len(keypoints)):
        raise InvalidValue(name, f"keypoint indices must lie in [0, {len(keypoints)})")
    return m


def _sample_colors(image, xy: np.ndarray) -> np.ndarray:
    """Colours ``(N, 3)`` in [0, 1] of the pixels nearest to ``xy``."""
    cols = np.clip(np.round(xy[:, 0]).astype(int), 0, image.width - 1)
    rows = np.clip(np.round(xy[:, 1]).astype(int), 0, image.height - 1)
    values = image.pixels[rows, cols].astype(np.float64)
    return values if values.ndim == 2 else np.repeat(values[:, None], 3, axis=1)


def _poses_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.concatenate([R, t[..., None]], axis=-1)


def _ray_angles_deg(centers: np.ndarray, X: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Largest angle (deg) between two rays from the observing camera centres to each point.

    ``centers`` ``(V, 3)``, ``X`` ``(n, 3)``, ``mask`` ``(V, n)``; a point seen once gets 0.
    """
    rays = X[None] - centers[:, None]  # (V, n, 3)
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-300)
    cos = np.einsum("ank,bnk->nab", rays, rays)
    both = mask.T[:, :, None] & mask.T[:, None, :]
    cos = np.where(both, cos, 1.0)
    return np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0)))


def _registered_cameras(images: ImageSet, K: np.ndarray, poses: np.ndarray, registered: np.ndarray,
                        colors: np.ndarray | None = None) -> Cameras:
    views = np.flatnonzero(registered)
    return Cameras(K=K[views], R=poses[views, :, :3], t=poses[views, :, 3], width=images[0].width,
                   height=images[0].height, image="images", views=views, colors=colors)


@dataclass
class _Model:
    """The reconstruction while it grows (mutable inside a step; the state gets copies)."""

    poses: np.ndarray  # (V, 3, 4)
    registered: np.ndarray  # (V,) bool
    points: np.ndarray  # (P, 3)
    point_tracks: np.ndarray  # (P,) int
    observed: np.ndarray  # (N,) bool

    def point_of_track(self, num_tracks: int) -> np.ndarray:
        size = max(num_tracks, int(self.point_tracks.max()) + 1 if len(self.point_tracks) else 0)
        out = np.full(size, -1, dtype=np.int64)
        out[self.point_tracks] = np.arange(len(self.point_tracks))
        return out

    def observations(self, keypoints: Points2D, track_of: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(keypoint index, view, point index)`` of every usable observation of a reconstructed point."""
        num_tracks = int(track_of.max()) + 1 if len(track_of) and track_of.max() >= 0 else 0
        of_track = self.point_of_track(num_tracks)
        point = np.where(track_of >= 0, of_track[np.maximum(track_of, 0)], -1) if num_tracks else \
            np.full(len(track_of), -1)
        use = (point >= 0) & self.registered[keypoints.view] & self.observed
        kp = np.flatnonzero(use)
        return kp, keypoints.view[kp], point[kp]

    def copy(self) -> _Model:
        return _Model(self.poses.copy(), self.registered.copy(), self.points.copy(), self.point_tracks.copy(),
                      self.observed.copy())


def _project(model: _Model, K: np.ndarray, views: np.ndarray, points: np.ndarray,
             X: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(n, 2)`` and depths ``(n,)`` of ``points`` (or of positions ``X``) in ``views``."""
    X = model.points[points] if X is None else X
    Xc = np.einsum("nij,nj->ni", model.poses[views, :, :3], X) + model.poses[views, :, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.einsum("nij,nj->ni", K[views], Xc / Xc[:, 2:3])[:, :2]
    return uv, Xc[:, 2]


def _observation_errors(model: _Model, K: np.ndarray, keypoints: Points2D, kp: np.ndarray, views: np.ndarray,
                        points: np.ndarray, X: np.ndarray | None = None) -> np.ndarray:
    """Reprojection error (px) of each observation ``(keypoint, view, point)`` (the point at ``X`` when
    given); ``inf`` behind the camera."""
    uv, depth = _project(model, K, views, points, X)
    errors = np.linalg.norm(uv - keypoints.xy[kp], axis=1)
    return np.where((depth > 0) & np.isfinite(errors), errors, np.inf)


def _point_colors(images: ImageSet, keypoints: Points2D, model: _Model, track_of: np.ndarray) -> np.ndarray:
    """Mean colour over each point's observations ``(P, 3)``."""
    kp, _, point = model.observations(keypoints, track_of)
    colors = keypoints.colors if keypoints.colors is not None else np.full((len(keypoints), 3), 0.7)
    sums = np.zeros((len(model.points), 3))
    np.add.at(sums, point, colors[kp])
    counts = np.bincount(point, minlength=len(model.points))[:, None]
    return np.where(counts > 0, sums / np.maximum(counts, 1), 0.7)


def _drawn(images: ImageSet, K: np.ndarray, keypoints: Points2D, model: _Model,
           track_of: np.ndarray) -> tuple[Cameras, PointCloud, Points2D]:
    kp, views, point = model.observations(keypoints, track_of)
    cloud = PointCloud(model.points, colors=np.clip(_point_colors(images, keypoints, model, track_of), 0, 1))
    observations = Points2D(keypoints.xy[kp], view=views, ids=point, image="images")
    return _registered_cameras(images, K, model.poses, model.registered), cloud, observations


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
    images = _images(images)
    xy, view, descriptors, colors, warnings = [], [], [], [], []
    for first in range(0, len(images), 2):
        second = min(first + 1, len(images) - 1)
        found = epipolar.detect_features(ImageSet((images[first], images[second])), max_features=max_features,
                                         contrast_threshold=contrast_threshold)
        for local, index in ((0, first), (1, second)):
            if local == 1 and second == first:
                continue
            keep = found.keypoints.view == local
            points = found.keypoints.xy[keep]
            xy.append(points)
            view.append(np.full(len(points), index, dtype=np.int64))
            descriptors.append(found.descriptors[keep])
            colors.append(_sample_colors(images[index], points))
            if len(points) < 50:
                warnings.append(f"{images.names[index]} (image {index}): only {len(points)} keypoints")
    counts = [len(p) for p in xy]
    keypoints = Points2D(np.concatenate(xy), view=np.concatenate(view), colors=np.concatenate(colors), image="images")
    return Features(keypoints, np.concatenate(descriptors).astype(np.float32), tuple(warnings), int(sum(counts)),
                    int(min(counts)))


@step_result
class PairMatches:
    """Result of :func:`match_all_pairs`."""

    matches: np.ndarray
    pair_matches: Curve
    warnings: Warnings
    pairs: int = metric("image pairs matched")
    num_matches: int = metric("matches in all pairs")


def image_pairs(count: int, *, pairs: str = "exhaustive", window: int = 3) -> list[tuple[int, int]]:
    """The pairs ``(a, b)``, ``a < b``, to match: all of them, or each image with the next ``window`` ones."""
    if pairs == "exhaustive":
        return [(a, b) for a in range(count) for b in range(a + 1, count)]
    return [(a, b) for a in range(count) for b in range(a + 1, min(count, a + 1 + int(window)))]


def match_all_pairs(keypoints: Points2D, descriptors: np.ndarray, *, ratio: Annotated[float, Range(0.05, 1.0)] = 0.8,
                    mutual: bool = True, pairs: Literal["exhaustive", "sequential"] = "exhaustive",
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
    keypoints = _keypoints(keypoints)
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2 or len(descriptors) != len(keypoints):
        raise InvalidValue("descriptors", f"expected one row per keypoint ({len(keypoints)}), got {descriptors.shape}")
    if views < 2:
        raise InvalidValue("keypoints", f"structure from motion needs keypoints in at least two images, got {views}")
    index = [np.flatnonzero(keypoints.view == v) for v in range(views)]
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
    chart = Curve(np.arange(len(counts), dtype=np.float64), np.asarray(counts, dtype=np.float64).reshape(1, -1),
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


def _pair_parallax(x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray, R: np.ndarray,
                   t: np.ndarray) -> float:
    """Median angle (deg) between the two rays of each correspondence under the relative pose ``(R, t)``."""
    r1 = np.column_stack([x1, np.ones(len(x1))]) @ np.linalg.inv(K1).T
    r2 = (np.column_stack([x2, np.ones(len(x2))]) @ np.linalg.inv(K2).T) @ R  # in camera 1's frame
    cos = np.sum(r1 * r2, axis=1) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1))
    return float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))


def verify_pairs(images: ImageSet, keypoints: Points2D, matches: np.ndarray, K: np.ndarray, *,
                 threshold_px: Annotated[float, Range(0.1, 20.0)] = 1.5,
                 min_inliers: Annotated[int, Range(8, 10000)] = 20,
                 max_iterations: Annotated[int, Range(10, 100000)] = 2000, rng: np.random.Generator) -> VerifiedPairs:
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
    images = _images(images)
    keypoints = _keypoints(keypoints, len(images))
    matches = _matches(matches, "matches", keypoints)
    K = check_intrinsics(K, images)
    keep = np.zeros(len(matches), dtype=bool)
    graph, poses, labels, warnings = [], [], [], []
    rejected = 0
    pair_keys = np.unique(matches[:, :2], axis=0) if len(matches) else np.zeros((0, 2), dtype=np.int64)
    for a, b in pair_keys:
        rows = np.flatnonzero((matches[:, 0] == a) & (matches[:, 1] == b))
        x1, x2 = keypoints.xy[matches[rows, 2]], keypoints.xy[matches[rows, 3]]
        if len(rows) < min_inliers:
            rejected += 1
            continue
        try:
            fit = epipolar.estimate_fundamental_ransac(x1, x2, threshold_px=threshold_px, confidence=0.999,
                                                       max_iterations=max_iterations, check_degenerate=False, rng=rng)
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
        angle = _pair_parallax(x1[inliers], x2[inliers], K[a], K[b], pose[:, :3], pose[:, 3])
        graph.append([a, b, len(rows), int(inliers.sum()), angle])
        poses.append(pose)
        labels.append(f"{a}-{b}")
    view_graph = np.array(graph, dtype=np.float64).reshape(-1, 5)
    connected = set(view_graph[:, :2].astype(int).ravel().tolist())
    lonely = [f"{images.names[v]} (image {v})" for v in range(len(images)) if v not in connected]
    if lonely:
        warnings.append(f"no verified pair for {', '.join(lonely)}: they share no (consistent) matches with any other "
                        "image and cannot be registered")
    chart = Curve(np.arange(len(graph), dtype=np.float64), view_graph[:, 3].reshape(1, -1), kind="bar",
                  title="Inliers per verified pair", xlabel="pair", ylabel="inliers", categories=tuple(labels))
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


def unit_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """Descriptors scaled to unit length ``(N, D)`` float64 (SIFT's L2 normalization; zero rows stay zero)."""
    d = np.asarray(descriptors, dtype=np.float64)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def _unit_descriptors_of(descriptors: Any, keypoints: Points2D) -> np.ndarray | None:
    """:func:`unit_descriptors` of an optional input, checked to have one row per keypoint (None stays None)."""
    if descriptors is None:
        return None
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2 or len(descriptors) != len(keypoints):
        raise InvalidValue("descriptors", f"expected one row per keypoint ({len(keypoints)}), got {descriptors.shape}")
    return unit_descriptors(descriptors)


def split_inconsistent(edges: np.ndarray, view: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
    """Cut an inconsistent match graph into consistent tracks: a union-find that never joins two sets sharing a view.

    ``edges`` ``(E, 2)`` keypoint indices (local, ``0 .. n-1``), ``view`` ``(n,)`` the image of each
    keypoint, ``order`` the order in which the edges are tried (best first, e.g. by descriptor
    distance; default: as given). An edge whose two sets already see a common image is cut: it is
    the one that would put two keypoints of one image into one track. Every consistent part of the
    component survives (a plain chain through the component keeps all its edges); only the
    conflicting, weakest edges go. Returns ``(n,)`` labels ``0 .. n-1`` (the root of each set).

    This sequential loop runs on the keypoints of inconsistent components only (a few hundred
    edges). COLMAP reaches the same end by never adding a second observation of one image to a
    track (``IncrementalTriangulator``); Moulon and Monasse build tracks with the same union-find
    but drop a track that sees an image twice (what :func:`build_tracks` did before).

    Reference: Schönberger and Frahm, "Structure-from-Motion Revisited", CVPR 2016, section 4.5;
    Moulon and Monasse, "Unordered feature tracking made fast and easy", CVMP 2012.
    """
    n = len(view)
    parent = list(range(n))
    seen = [1 << int(v) for v in view]  # views of each set as a bit mask (any number of views)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    order = np.arange(len(edges)) if order is None else np.asarray(order)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in edges[order].tolist():
        ra, rb = find(a), find(b)
        if ra == rb or seen[ra] & seen[rb]:
            continue
        parent[rb] = ra
        seen[ra] |= seen[rb]
    return np.array([find(i) for i in range(n)], dtype=np.int64)


def build_tracks(keypoints: Points2D, inlier_matches: np.ndarray, descriptors: np.ndarray | None = None) -> Tracks:
    """Join the verified matches into tracks: the connected components of the match graph, inconsistent ones split.

    Nodes are keypoints, edges the inlier matches; a component is one 3D point seen in several
    images (union-find, here ``scipy.sparse.csgraph.connected_components``). A component with two
    keypoints in one image is inconsistent (a wrong match somewhere); it is not dropped but split
    (:func:`split_inconsistent`): its edges are re-joined best first (smallest descriptor distance
    when ``descriptors`` are given) and an edge that would make a track see one image twice is cut,
    so the consistent part of the component is kept.

    Returns ``track_of`` ``(N,)`` int, the track of each keypoint (-1: none), tracks numbered 0 ..

    Reference: Schönberger and Frahm (2016), sections 3.1 (scene graph) and 4.5 (a track sees an
    image once); Snavely et al., "Photo tourism" (2006), section 4.1.
    """
    import scipy.sparse
    from scipy.sparse.csgraph import connected_components

    keypoints = _keypoints(keypoints)
    m = _matches(inlier_matches, "inlier_matches", keypoints)
    n = len(keypoints)
    track_of = np.full(n, -1, dtype=np.int64)
    if not len(m):
        return Tracks(track_of, ("no verified matches: no tracks",), 0, 0.0, 0, 0, 0, 0)
    unit = _unit_descriptors_of(descriptors, keypoints)
    graph = scipy.sparse.coo_matrix((np.ones(len(m)), (m[:, 2], m[:, 3])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    candidate = sizes[labels] >= 2
    # a component is consistent when its keypoints lie in distinct views
    stride = int(keypoints.view.max()) + 1
    key = labels.astype(np.int64) * stride + keypoints.view
    distinct = np.unique(key[candidate])
    views_per_label = np.bincount(distinct // stride, minlength=len(sizes))
    bad_label = (sizes >= 2) & (views_per_label < sizes)
    consistent = candidate & ~bad_label[labels]
    labels = labels.astype(np.int64)
    inconsistent = int(bad_label.sum())
    split, cut, dropped = 0, 0, 0
    if inconsistent:
        members = np.flatnonzero(bad_label[labels])
        local = np.full(n, -1, dtype=np.int64)
        local[members] = np.arange(len(members))
        edges = m[bad_label[labels[m[:, 2]]]][:, 2:]
        order = None
        if unit is not None:
            order = np.argsort(np.linalg.norm(unit[edges[:, 0]] - unit[edges[:, 1]], axis=1), kind="stable")
        root = split_inconsistent(local[edges], keypoints.view[members], order)
        part = members[root]  # a keypoint index names each part, distinct from every component label
        part_sizes = np.bincount(root, minlength=len(members))
        keep = part_sizes[root] >= 2
        labels[members] = len(sizes) + part  # new labels beyond the components'
        consistent[members[keep]] = True
        split = int(len(np.unique(root[keep])))
        cut = int(np.sum(root[local[edges[:, 0]]] != root[local[edges[:, 1]]]))
        dropped = int(np.sum(~keep))
    kept, renumbered = np.unique(labels[consistent], return_inverse=True)
    track_of[consistent] = renumbered.reshape(-1)
    count = len(kept)
    mean = float(consistent.sum() / count) if count else 0.0
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


def _pair_rows(matches: np.ndarray, a: int, b: int) -> np.ndarray:
    return np.flatnonzero((matches[:, 0] == a) & (matches[:, 1] == b))


def _initial(initial_pair: Any, views: int) -> tuple[int, int]:
    pair = np.asarray(initial_pair).reshape(-1)
    if pair.shape != (2,) or not np.issubdtype(pair.dtype, np.integer) or pair.min() < 0 or pair.max() >= views \
            or pair[0] == pair[1]:
        raise InvalidValue("initial_pair", f"expected two different image indices in [0, {views}), got {pair}")
    return int(pair[0]), int(pair[1])


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
    images = _images(images)
    keypoints = _keypoints(keypoints, len(images))
    m = _matches(inlier_matches, "inlier_matches", keypoints)
    K = check_intrinsics(K, images)
    a, b = _initial(initial_pair, len(images))
    rows = _pair_rows(m, min(a, b), max(a, b))
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
    return InitialPose(_poses_matrix(refined.R, refined.t), refined.warnings, int(fit.inliers.sum()),
                       int(counts.max()), refined.sampson_rms_px, refined.median_parallax_deg)


# ----------------------------------------------------------------------------------------------------
# 5. Triangulating the initial pair: linear, then non-linear
# ----------------------------------------------------------------------------------------------------
def _pair_observations(keypoints: Points2D, track_of: np.ndarray, a: int, b: int) -> tuple[np.ndarray, ...]:
    """Tracks seen in views ``a`` and ``b``: ``(tracks, keypoint in a, keypoint in b)``."""
    in_a = np.flatnonzero((keypoints.view == a) & (track_of >= 0))
    in_b = np.flatnonzero((keypoints.view == b) & (track_of >= 0))
    common, ia, ib = np.intersect1d(track_of[in_a], track_of[in_b], return_indices=True)
    return common, in_a[ia], in_b[ib]


def _track_of(value: Any, keypoints: Points2D, name: str = "track_of") -> np.ndarray:
    track_of = np.asarray(value)
    if track_of.shape != (len(keypoints),) or not np.issubdtype(track_of.dtype, np.integer):
        raise InvalidValue(name, f"expected ({len(keypoints)},) integer track ids, got {track_of.shape}")
    return track_of.astype(np.int64)


def _track_lengths(track_of: np.ndarray) -> np.ndarray:
    """Keypoints (images) in each track ``(T,)``."""
    return np.bincount(track_of[track_of >= 0], minlength=int(track_of.max()) + 1 if len(track_of) else 0)


def _model_tracks(track_of: Any, model_track_of: Any, keypoints: Points2D) -> np.ndarray:
    """The incremental model's tracks when given, else ``build_tracks``' (both checked)."""
    if model_track_of is None:
        return _track_of(track_of, keypoints)
    return _track_of(model_track_of, keypoints, "model_track_of")


@step_result
class InitialPoints:
    """Result of :func:`triangulate_initial`."""

    initial_points_dlt: np.ndarray
    initial_point_tracks: np.ndarray
    warnings: Warnings
    points: int = metric("points kept")
    dropped_behind: int = metric("points behind a camera, dropped")
    dropped_angle: int = metric("points with a too small triangulation angle, dropped")
    reprojection_rms_px: float = metric("RMS reprojection error of the DLT points", unit="px")
    ignored_two_view: int = metric("tracks seen by the two initial images only, not triangulated")


def triangulate_initial(keypoints: Points2D, track_of: np.ndarray, K: np.ndarray, initial_pair: np.ndarray,
                        initial_pose: np.ndarray, *, min_angle_deg: Annotated[float, Range(0.0, 30.0)] = 1.0,
                        ignore_two_view_tracks: bool = True) -> InitialPoints:
    """Linear (DLT) triangulation of the tracks seen in both initial views (``triangulate_dlt``).

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

    Returns ``initial_points_dlt`` ``(P, 3)`` and their tracks ``initial_point_tracks`` ``(P,)``.
    Corresponds to ``cv2.triangulatePoints(P1, P2, x1.T, x2.T)``.

    Reference: H&Z section 12.2.
    """
    keypoints = _keypoints(keypoints)
    track_of = _track_of(track_of, keypoints)
    K = np.asarray(K, dtype=np.float64)
    a, b = _initial(initial_pair, len(K))
    pose = np.asarray(initial_pose, dtype=np.float64).reshape(3, 4)
    tracks, ka, kb = _pair_observations(keypoints, track_of, a, b)
    ignored = 0
    if ignore_two_view_tracks:
        longer = _track_lengths(track_of)[tracks] > 2
        ignored = int(np.sum(~longer))
        tracks, ka, kb = tracks[longer], ka[longer], kb[longer]
    if len(tracks) < PNP_MINIMUM:
        raise InvalidValue("track_of", f"images {a} and {b} share only {len(tracks)} tracks: choose another pair")
    P = np.stack([projection_matrix(K[a], np.eye(3), np.zeros(3)), projection_matrix(K[b], pose[:, :3], pose[:, 3])])
    x = np.stack([keypoints.xy[ka], keypoints.xy[kb]])
    X = triangulate_dlt(P, x)
    finite = np.all(np.isfinite(X), axis=1)
    X = np.where(finite[:, None], X, 0.0)
    front = finite & np.all(point_depths(P, X) > 0, axis=0)
    centers = np.stack([np.zeros(3), -pose[:, :3].T @ pose[:, 3]])
    angle = _ray_angles_deg(centers, X, np.ones((2, len(X)), dtype=bool))
    wide = angle >= min_angle_deg
    keep = front & wide
    from lab.geometry.triangulation import reprojection_residuals

    residual = reprojection_residuals(P, X[keep], x[:, keep])
    rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=2)))) if keep.any() else 0.0
    warnings = () if keep.sum() >= 50 else (f"only {int(keep.sum())} points from the initial pair",)
    return InitialPoints(X[keep], tracks[keep], warnings, int(keep.sum()), int(np.sum(~front)),
                         int(np.sum(front & ~wide)), rms, ignored)


@step_result
class InitialModel:
    """Result of :func:`refine_initial_points`."""

    initial_poses: np.ndarray
    initial_registered: np.ndarray
    initial_points: np.ndarray
    initial_point_tracks: np.ndarray
    cameras: Cameras
    points3d: PointCloud
    triangulation_cost: Curve
    reprojection_rms_dlt_px: float = metric("RMS reprojection error of the DLT points (linear)", unit="px")
    reprojection_rms_px: float = metric("RMS reprojection error after non-linear triangulation", unit="px")
    points: int = metric("points of the two-view model")


def refine_initial_points(images: ImageSet, keypoints: Points2D, track_of: np.ndarray, K: np.ndarray,
                          initial_pair: np.ndarray, initial_pose: np.ndarray, initial_points_dlt: np.ndarray,
                          initial_point_tracks: np.ndarray, *,
                          iterations: Annotated[int, Range(0, 100)] = 10) -> InitialModel:
    """Non-linear triangulation: move each point to minimize its reprojection error in both views (cameras fixed).

    Levenberg-Marquardt per point on ``|pi(P1 X) - x1|^2 + |pi(P2 X) - x2|^2``
    (:func:`lab.geometry.triangulation.refine_points`), the maximum-likelihood point under
    Gaussian pixel noise where the DLT minimized an algebraic error. Then the two-view model: the
    first view at the origin, the second at ``initial_pose``.

    Args:
        iterations: most Levenberg-Marquardt iterations (0: keep the DLT points).

    Returns the two-view model (``initial_poses`` ``(V, 3, 4)``, ``initial_registered`` ``(V,)``,
    ``initial_points``, ``initial_point_tracks``), ``cameras``, ``points3d`` and the RMS per
    iteration. No single OpenCV call.

    Reference: H&Z section 12.5 (the maximum-likelihood criterion) and appendix A6.2.
    """
    images = _images(images)
    keypoints = _keypoints(keypoints, len(images))
    track_of = _track_of(track_of, keypoints)
    K = check_intrinsics(K, images)
    a, b = _initial(initial_pair, len(images))
    pose = np.asarray(initial_pose, dtype=np.float64).reshape(3, 4)
    X0 = np.asarray(initial_points_dlt, dtype=np.float64)
    tracks = np.asarray(initial_point_tracks, dtype=np.int64)
    if X0.shape != (len(tracks), 3):
        raise InvalidValue("initial_points_dlt", f"expected ({len(tracks)}, 3), got {X0.shape}")
    if not len(tracks):
        raise InvalidValue("initial_points_dlt", "no points to refine")
    first = {int(t): k for t, k in zip(track_of[keypoints.view == a], np.flatnonzero(keypoints.view == a)) if t >= 0}
    second = {int(t): k for t, k in zip(track_of[keypoints.view == b], np.flatnonzero(keypoints.view == b)) if t >= 0}
    ka = np.array([first[int(t)] for t in tracks])
    kb = np.array([second[int(t)] for t in tracks])
    P = np.stack([projection_matrix(K[a], np.eye(3), np.zeros(3)), projection_matrix(K[b], pose[:, :3], pose[:, 3])])
    X, history = refine_points(P, np.stack([keypoints.xy[ka], keypoints.xy[kb]]), X0, iterations=int(iterations))
    poses = np.zeros((len(images), 3, 4))
    poses[a] = _poses_matrix(np.eye(3), np.zeros(3))
    poses[b] = pose
    registered = np.zeros(len(images), dtype=bool)
    registered[[a, b]] = True
    model = _Model(poses, registered, X, tracks, np.ones(len(keypoints), dtype=bool))
    cameras, cloud, _ = _drawn(images, K, keypoints, model, track_of)
    cost = Curve(np.arange(len(history), dtype=np.float64), history, title="Non-linear triangulation",
                 xlabel="iteration", ylabel="RMS reprojection error (px)", labels=("RMS",))
    return InitialModel(poses, registered, X, tracks, cameras, cloud, cost, float(history[0]), float(history[-1]),
                        len(X))


# ----------------------------------------------------------------------------------------------------
# 6. The incremental loop: register, triangulate, bundle adjust
# ----------------------------------------------------------------------------------------------------
@step_result
class IncrementalModel:
    """Result of :func:`reconstruct_incrementally`."""

    poses: np.ndarray
    registered: np.ndarray
    points: np.ndarray
    point_tracks: np.ndarray
    observed: np.ndarray
    model_track_of: np.ndarray
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
    pnp_rms_linear_px: float = metric("RMS reprojection error of the PnP inliers, linear PnP (DLT in RANSAC), "
                                      "mean over registrations", unit="px")
    pnp_rms_nonlinear_px: float = metric("the same after non-linear PnP", unit="px")
    triangulation_rms_linear_px: float = metric("RMS reprojection error of the new points, DLT", unit="px")
    triangulation_rms_nonlinear_px: float = metric("the same after non-linear triangulation", unit="px")
    ba_rms_before_px: float = metric("RMS reprojection error before the last bundle adjustment", unit="px")
    ba_rms_after_px: float = metric("RMS reprojection error after the last bundle adjustment", unit="px")
    ba_never_raised: bool = metric("no bundle adjustment raised the RMS error")


def _model_from(poses: Any, registered: Any, points: Any, point_tracks: Any, views: int, keypoints: Points2D,
                observed: Any = None) -> _Model:
    poses = np.asarray(poses, dtype=np.float64)
    registered = np.asarray(registered, dtype=bool)
    points = np.asarray(points, dtype=np.float64)
    tracks = np.asarray(point_tracks, dtype=np.int64)
    if poses.shape != (views, 3, 4) or registered.shape != (views,):
        raise InvalidValue("poses", f"expected poses ({views}, 3, 4) and registered ({views},), got {poses.shape} and "
                                    f"{registered.shape}")
    if points.shape != (len(tracks), 3):
        raise InvalidValue("points", f"expected ({len(tracks)}, 3) points, one per track id, got {points.shape}")
    observed = np.ones(len(keypoints), dtype=bool) if observed is None else np.asarray(observed, dtype=bool)
    if observed.shape != (len(keypoints),):
        raise InvalidValue("observed", f"expected ({len(keypoints)},) bool, got {observed.shape}")
    return _Model(poses.copy(), registered.copy(), points.copy(), tracks.copy(), observed.copy())


def _bundle(model: _Model, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray, anchor: int, *, loss: str,
            f_scale: float, max_iterations: int, refine_intrinsics: bool = False):
    """Bundle adjustment of the model (generator: yields ``(iteration, rms)``, returns the BundleResult)."""
    kp, views, point = model.observations(keypoints, track_of)
    cams = np.flatnonzero(model.registered)
    local = np.full(len(model.registered), -1)
    local[cams] = np.arange(len(cams))
    used = np.unique(point)
    point_local = np.full(len(model.points), -1)
    point_local[used] = np.arange(len(used))
    K_sub = K[cams]
    if refine_intrinsics and np.allclose(K_sub, K_sub[0]):
        K_sub = K_sub[0]
    result = yield from bundle_adjust_progress(
        K_sub, model.poses[cams, :, :3], model.poses[cams, :, 3], model.points[used], local[views], point_local[point],
        keypoints.xy[kp], loss=loss, f_scale=f_scale, refine_intrinsics=refine_intrinsics,
        fixed_cameras=(int(local[anchor]),), max_iterations=max_iterations)
    model.poses[cams] = _poses_matrix(result.R, result.t)
    model.points[used] = result.points
    K_out = np.broadcast_to(result.K, (len(cams), 3, 3)) if result.K.ndim == 2 else result.K
    return result, cams, K_out


def _reject_outliers(model: _Model, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray,
                     max_error_px: float) -> int:
    """Stop using observations whose error exceeds ``max_error_px``; drop points left with < 2. Returns drops."""
    kp, views, point = model.observations(keypoints, track_of)
    errors = _observation_errors(model, K, keypoints, kp, views, point)
    bad = errors > max_error_px
    model.observed[kp[bad]] = False
    counts = np.bincount(point[~bad], minlength=len(model.points))
    keep = counts >= 2
    if not keep.all():
        model.points = model.points[keep]
        model.point_tracks = model.point_tracks[keep]
    return int(bad.sum())


def _triangulate_new(model: _Model, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray, tried: np.ndarray, *,
                     min_angle_deg: float, max_error_px: float, min_track_length: int = 2) -> tuple[int, float, float]:
    """Triangulate the tracks with two or more registered observations and no point yet (DLT, then LM).

    Only tracks of at least ``min_track_length`` keypoints (3: COLMAP's ``ignore_two_view_tracks``).

    Returns (new points, RMS before refinement, RMS after) over the new points' observations.
    """
    num_tracks = len(tried)
    has_point = np.zeros(num_tracks, dtype=bool)
    has_point[model.point_tracks] = True
    usable = (track_of >= 0) & model.registered[keypoints.view] & model.observed
    kp = np.flatnonzero(usable)
    kp = kp[~has_point[track_of[kp]]]
    counts = np.bincount(track_of[kp], minlength=num_tracks)
    lengths = np.bincount(track_of[track_of >= 0], minlength=num_tracks)
    candidates = np.flatnonzero((counts >= 2) & (counts > tried) & (lengths >= min_track_length))
    if not len(candidates):
        return 0, 0.0, 0.0
    tried[candidates] = counts[candidates]
    cams = np.flatnonzero(model.registered)
    local = np.full(len(model.registered), -1)
    local[cams] = np.arange(len(cams))
    column = np.full(num_tracks, -1)
    column[candidates] = np.arange(len(candidates))
    kp = kp[column[track_of[kp]] >= 0]
    x = np.zeros((len(cams), len(candidates), 2))
    mask = np.zeros((len(cams), len(candidates)), dtype=bool)
    rows, cols = local[keypoints.view[kp]], column[track_of[kp]]
    x[rows, cols] = keypoints.xy[kp]
    mask[rows, cols] = True
    P = projection_matrix(K[cams], model.poses[cams, :, :3], model.poses[cams, :, 3])
    X = triangulate_dlt(P, x, mask)
    finite = np.all(np.isfinite(X), axis=1)
    X = np.where(finite[:, None], X, 0.0)
    depths = point_depths(P, X)
    front = finite & np.all((depths > 0) | ~mask, axis=0)
    centers = -np.einsum("vji,vj->vi", model.poses[cams, :, :3], model.poses[cams, :, 3])
    wide = _ray_angles_deg(centers, X, mask) >= min_angle_deg
    keep = front & wide
    if not keep.any():
        return 0, 0.0, 0.0
    X_refined, history = refine_points(P, x[:, keep], X[keep], mask[:, keep], iterations=10)
    projected = np.einsum("vij,nj->vni", P[:, :, :3], X_refined) + P[:, None, :, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        errors = np.linalg.norm(projected[..., :2] / projected[..., 2:] - x[:, keep], axis=2)
    errors = np.where(mask[:, keep], errors, 0.0)
    good = np.all(np.isfinite(errors) & (errors <= max_error_px), axis=0)
    good &= np.all((np.einsum("vij,nj->vni", P[:, 2:3, :3], X_refined)[..., 0] + P[:, None, 2, 3] > 0)
                   | ~mask[:, keep], axis=0)
    if not good.any():
        return 0, 0.0, 0.0
    chosen = candidates[keep][good]
    model.points = np.concatenate([model.points, X_refined[good]])
    model.point_tracks = np.concatenate([model.point_tracks, chosen])
    return int(good.sum()), float(history[0]), float(history[-1])


# --- COLMAP's incremental triangulator: continue, complete and merge tracks (Schönberger and Frahm 2016, 4.5) ---
def _continue_tracks(model: _Model, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray, view: int, *,
                     max_error_px: float) -> int:
    """Track continuation: the new image's keypoints whose tracks already have a point become observations
    when they reproject within ``max_error_px`` under its refined pose (PnP outliers that fit it come back).

    Returns the observations the image adds. COLMAP's ``IncrementalTriangulator::Continue``.
    """
    kp, point = _correspondences_2d3d(model, keypoints, track_of, view, all_keypoints=True)
    if not len(kp):
        return 0
    good = _observation_errors(model, K, keypoints, kp, np.full(len(kp), view), point) <= max_error_px
    model.observed[kp] = good
    return int(good.sum())


def _guided_candidates(model: _Model, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray,
                       unit: np.ndarray | None, trees: dict, sizes: np.ndarray, *, max_error_px: float,
                       max_descriptor_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints that may observe a point in a registered image where it has no observation yet.

    Every point is projected into every registered image its track does not observe; the keypoints
    within ``max_error_px`` of the projection (a k-d tree per image, ``scipy.spatial.cKDTree``)
    whose unit descriptor lies within ``max_descriptor_distance`` of one of the point's observations
    (compare COLMAP's matcher ``max_distance``) are candidates; without descriptors only a keypoint alone in
    that radius is. This is the guided search of H&Z algorithm 11.4 step (v) with the projection
    of the point as the search region: the correspondences the ratio test missed.

    Returns ``(point, keypoint, error px)`` rows, several per point possible.
    """
    empty = (np.zeros(0, dtype=np.int64),) * 2 + (np.zeros(0),)
    if not len(model.points):
        return empty
    kp, views, point = model.observations(keypoints, track_of)
    V = len(model.registered)
    seen = np.zeros((len(model.points), V), dtype=bool)
    seen[point, views] = True
    cams = np.flatnonzero(model.registered)
    pp, column = np.nonzero(~seen[:, cams])
    vv = cams[column]
    uv, depth = _project(model, K, vv, pp)
    inside = (depth > 0) & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= -0.5) & (uv[:, 1] >= -0.5) \
        & (uv[:, 0] <= sizes[vv, 0] - 0.5) & (uv[:, 1] <= sizes[vv, 1] - 0.5)
    pp, vv, uv = pp[inside], vv[inside], uv[inside]
    neighbours = 3 if unit is not None else 2
    found_p, found_k, found_e = [], [], []
    for v in np.unique(vv):
        rows = np.flatnonzero(vv == v)
        tree, index = trees[int(v)]
        if tree.n == 0:
            continue
        distance, nearest = tree.query(uv[rows], k=neighbours, distance_upper_bound=max_error_px)
        if unit is None:  # no descriptors: only an unambiguous keypoint
            alone = np.isfinite(distance[:, 0]) & ~np.isfinite(distance[:, 1])
            distance, nearest, rows = distance[alone, :1], nearest[alone, :1], rows[alone]
        hit = np.isfinite(distance)
        found_p.append(np.broadcast_to(pp[rows, None], hit.shape)[hit])
        found_k.append(index[nearest[hit]])
        found_e.append(distance[hit])
    if not found_p:
        return empty
    cp, ck, ce = np.concatenate(found_p), np.concatenate(found_k), np.concatenate(found_e)
    if unit is not None and len(cp):
        # smallest descriptor distance from each candidate to the observations of its point
        order = np.argsort(point, kind="stable")
        obs_kp = kp[order]
        counts = np.bincount(point, minlength=len(model.points))
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        n = counts[cp]
        has = n > 0
        cp, ck, ce, n = cp[has], ck[has], ce[has], n[has]
        pair = np.repeat(np.arange(len(cp)), n)
        offset = np.arange(len(pair)) - np.repeat(np.cumsum(n) - n, n)
        distance = np.linalg.norm(unit[ck[pair]] - unit[obs_kp[starts[cp][pair] + offset]], axis=1)
        best = np.minimum.reduceat(distance, np.cumsum(n) - n) if len(pair) else np.zeros(0)
        close = best <= max_descriptor_distance
        cp, ck, ce = cp[close], ck[close], ce[close]
    return cp, ck, ce


def _complete_tracks(model: _Model, keypoints: Points2D, track_of: np.ndarray,
                     candidates: tuple[np.ndarray, np.ndarray, np.ndarray]) -> int:
    """Track completion: attach to each point the free keypoints of :func:`_guided_candidates` (in place).

    A keypoint is free when it observes no point. Each keypoint goes to the point it fits best and
    each point takes at most one keypoint per image (the smallest error); the keypoint joins the
    point's track (``track_of`` changes), and an unused keypoint the track had in that image leaves
    it, so a track still sees each image once. Returns the observations added. COLMAP's
    ``IncrementalTriangulator::Complete``.
    """
    cp, ck, ce = candidates
    kp, _, point = model.observations(keypoints, track_of)
    point_of = np.full(len(keypoints), -1, dtype=np.int64)
    point_of[kp] = point
    free = point_of[ck] < 0
    cp, ck, ce = cp[free], ck[free], ce[free]
    if not len(cp):
        return 0
    order = np.argsort(ce, kind="stable")
    cp, ck = cp[order], ck[order]
    _, first = np.unique(ck, return_index=True)
    cp, ck = cp[np.sort(first)], ck[np.sort(first)]
    V = len(model.registered)
    slot = cp * V + keypoints.view[ck]
    _, first = np.unique(slot, return_index=True)
    cp, ck = cp[np.sort(first)], ck[np.sort(first)]
    target = model.point_tracks[cp]
    labelled = np.flatnonzero(track_of >= 0)
    stale = labelled[np.isin(track_of[labelled] * V + keypoints.view[labelled], target * V + keypoints.view[ck])]
    track_of[stale] = -1
    track_of[ck] = target
    model.observed[ck] = True
    return len(ck)


def _merge_tracks(model: _Model, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray,
                  candidates: tuple[np.ndarray, np.ndarray, np.ndarray], *, max_error_px: float) -> int:
    """Track merging: two points whose projections land on each other's observations become one (in place).

    A candidate of :func:`_guided_candidates` that already observes another point links the two.
    They merge when their tracks see no image in common and every observation of both lies within
    ``max_error_px`` of the merged point, the mean of the two weighted by their observation counts
    (COLMAP's ``IncrementalTriangulator::Merge``). Each point takes part in at most one merge per
    call (best first). Returns the merges made.
    """
    cp, ck, _ = candidates
    kp, views, point = model.observations(keypoints, track_of)
    point_of = np.full(len(keypoints), -1, dtype=np.int64)
    point_of[kp] = point
    other = point_of[ck]
    linked = (other >= 0) & (other != cp)
    if not linked.any():
        return 0
    pairs = np.unique(np.sort(np.column_stack([cp[linked], other[linked]]), axis=1), axis=0)
    V = len(model.registered)
    ta, tb = model.point_tracks[pairs[:, 0]], model.point_tracks[pairs[:, 1]]
    involved, local = np.unique(np.concatenate([ta, tb]), return_inverse=True)
    labelled = np.flatnonzero(np.isin(track_of, involved))
    sees = np.zeros((len(involved), V), dtype=bool)
    sees[np.searchsorted(involved, track_of[labelled]), keypoints.view[labelled]] = True
    la, lb = local[:len(pairs)], local[len(pairs):]
    pairs = pairs[~np.any(sees[la] & sees[lb], axis=1)]
    if not len(pairs):
        return 0
    counts = np.bincount(point, minlength=len(model.points)).astype(np.float64)
    na, nb = counts[pairs[:, 0]], counts[pairs[:, 1]]
    merged = (na[:, None] * model.points[pairs[:, 0]] + nb[:, None] * model.points[pairs[:, 1]]) / (na + nb)[:, None]
    # worst reprojection error of the merged point over the observations of both points
    slot = np.full(len(model.points), -1, dtype=np.int64)
    worst = np.zeros(len(pairs))
    for side in (0, 1):
        slot[:] = -1
        slot[pairs[:, side]] = np.arange(len(pairs))
        rows = np.flatnonzero(slot[point] >= 0)
        error = _observation_errors(model, K, keypoints, kp[rows], views[rows], point[rows], merged[slot[point[rows]]])
        np.maximum.at(worst, slot[point[rows]], error)
    good = worst <= max_error_px
    pairs, merged, worst = pairs[good], merged[good], worst[good]
    if not len(pairs):
        return 0
    order = np.argsort(worst, kind="stable")
    pairs, merged = pairs[order], merged[order]
    sequence = pairs.reshape(-1)  # a point may merge once per call: keep pairs whose points appear first there
    _, first = np.unique(sequence, return_index=True)
    first_of = np.full(len(model.points), -1)
    first_of[sequence[first]] = first
    rank = 2 * np.arange(len(pairs))
    alone = (first_of[pairs[:, 0]] == rank) & (first_of[pairs[:, 1]] == rank + 1)
    pairs, merged = pairs[alone], merged[alone]
    model.points[pairs[:, 0]] = merged
    remap = np.arange(max(int(track_of.max()) + 1, 1))
    remap[model.point_tracks[pairs[:, 1]]] = model.point_tracks[pairs[:, 0]]
    labelled = track_of >= 0
    track_of[labelled] = remap[track_of[labelled]]
    keep = np.ones(len(model.points), dtype=bool)
    keep[pairs[:, 1]] = False
    model.points, model.point_tracks = model.points[keep], model.point_tracks[keep]
    return len(pairs)


def _complete_and_merge(model: _Model, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray,
                        unit: np.ndarray | None, trees: dict, sizes: np.ndarray, *, max_error_px: float,
                        max_descriptor_distance: float, rounds: int = 1) -> tuple[int, int]:
    """Complete, then merge tracks, ``rounds`` times or until nothing changes: ``(observations added, merges)``.

    COLMAP's ``IncrementalTriangulator::CompleteAndMergeTracks``.
    """
    completed = merged = 0
    for _ in range(rounds):
        options = dict(max_error_px=max_error_px, max_descriptor_distance=max_descriptor_distance)
        added = _complete_tracks(model, keypoints, track_of,
                                 _guided_candidates(model, K, keypoints, track_of, unit, trees, sizes, **options))
        joined = _merge_tracks(model, K, keypoints, track_of,
                               _guided_candidates(model, K, keypoints, track_of, unit, trees, sizes, **options),
                               max_error_px=max_error_px)
        completed, merged = completed + added, merged + joined
        if not added and not joined:
            break
    return completed, merged


def _drop_two_view_points(model: _Model, track_of: np.ndarray, tried: np.ndarray) -> int:
    """Drop the points whose tracks still have two keypoints after completion (in place); returns how many.

    With completion on, a two-view track is triangulated on trial: completion may find it in a
    third image (then it stays), else it goes, as COLMAP's ``ignore_two_view_tracks`` would never
    have made it; it is tried again after the next registration.
    """
    short = _track_lengths(track_of)[model.point_tracks] < 3
    if short.any():
        tried[model.point_tracks[short]] = 0
        model.points, model.point_tracks = model.points[~short], model.point_tracks[~short]
    return int(short.sum())


def _keypoint_trees(keypoints: Points2D, views: int) -> dict:
    """One k-d tree per image over its keypoints, with their global indices: ``{view: (tree, index)}``."""
    from scipy.spatial import cKDTree

    trees = {}
    for v in range(views):
        index = np.flatnonzero(keypoints.view == v)
        trees[v] = (cKDTree(keypoints.xy[index] if len(index) else np.zeros((0, 2))), np.append(index, -1))
    return trees


def _correspondences_2d3d(model: _Model, keypoints: Points2D, track_of: np.ndarray, view: int, *,
                          all_keypoints: bool = False):
    """``(keypoints, points)`` of ``view`` whose tracks have a point (the still-used ones, all if ``all_keypoints``)."""
    of_track = model.point_of_track(max(len(track_of) and int(track_of.max()) + 1, 1))
    kp = np.flatnonzero((keypoints.view == view) & (track_of >= 0) & (model.observed | all_keypoints))
    point = of_track[track_of[kp]] if len(kp) else np.zeros(0, dtype=np.int64)
    kp, point = kp[point >= 0], point[point >= 0]
    return kp, point


def reconstruct_incrementally(images: ImageSet, keypoints: Points2D, track_of: np.ndarray, K: np.ndarray,
                              initial_pair: np.ndarray, initial_poses: np.ndarray, initial_registered: np.ndarray,
                              initial_points: np.ndarray, initial_point_tracks: np.ndarray,
                              descriptors: np.ndarray | None = None, *,
                              pnp_threshold_px: Annotated[float, Range(0.5, 50.0)] = 4.0,
                              min_correspondences: Annotated[int, Range(6, 10000)] = 20,
                              min_angle_deg: Annotated[float, Range(0.0, 30.0)] = 1.5,
                              max_error_px: Annotated[float, Range(0.5, 50.0)] = 4.0,
                              ba_loss: Literal["linear", "huber", "soft_l1", "cauchy", "arctan"] = "huber",
                              ba_iterations: Annotated[int, Range(0, 200)] = 5,
                              ba_growth: Annotated[float, Range(1.0, 10.0)] = 1.25,
                              complete_tracks: bool = True,
                              ignore_two_view_tracks: bool = True,
                              complete_max_error_px: Annotated[float, Range(0.1, 50.0)] = 2.0,
                              max_descriptor_distance: Annotated[float, Range(0.0, 2.0)] = 0.5,
                              rng: np.random.Generator,
                              ) -> Generator[Progress, None, IncrementalModel]:
    """Grow the two-view model one image at a time: register -> triangulate -> bundle adjust (a generator step).

    Repeat while an unregistered image sees at least ``min_correspondences`` reconstructed points
    (through its tracks), taking the one that sees most (Schönberger and Frahm 2016, section 4.2,
    "next best view"):

    1. **Register** it: linear PnP (DLT on 6-point samples, rotation orthonormalised with det +1)
       inside RANSAC (:func:`lab.geometry.pnp.pnp_ransac`, H&Z section 7.1), then non-linear PnP
       (:func:`lab.geometry.pnp.refine_pnp`: reprojection error over axis-angle and translation,
       H&Z section 7.2) on the inliers; outlier observations of the image are no longer used.
    2. **Triangulate** every track that now has two or more registered observations and no point
       (DLT over all its views, then Levenberg-Marquardt per point; H&Z sections 12.2 and 12.5), kept
       when in front of its cameras, with a triangulation angle of at least ``min_angle_deg`` and
       every reprojection error below ``max_error_px``.
    3. **Bundle adjust**, when the model has grown by ``ba_growth`` since the last time, all
       registered cameras and points (:func:`lab.geometry.bundle_adjustment.bundle_adjust`,
       sparse trust-region least squares with a robust loss, the first initial view held fixed and
       the scale held; Triggs et al. 2000), then stop using observations whose error exceeds
       ``max_error_px``.

    Tracks grow as in COLMAP's incremental triangulator (Schönberger and Frahm 2016, section 4.5;
    ``IncrementalTriangulator`` in ``src/colmap/sfm/incremental_triangulator.cc``):

    * **create** only points of three or more images when ``ignore_two_view_tracks`` (COLMAP's
      default): a two-view point is never checked by a third image nor helps register one. With
      completion on, a two-view track is triangulated on trial and kept only if completion finds
      it in a third image (:func:`_drop_two_view_points`);
    * **continue**: after registration, every keypoint of the new image whose track has a point
      becomes an observation if it reprojects within ``complete_max_error_px`` under the refined
      pose (PnP outliers that fit it come back);
    * **complete**: each point is projected into every registered image its track does not see;
      the keypoint nearest to the projection (within ``complete_max_error_px``, its descriptor
      within ``max_descriptor_distance`` of one of the point's) joins the track. COLMAP follows the
      correspondence graph here; the graph's gaps are the ratio test's, so the search is guided by
      the projection (H&Z algorithm 11.4, step v);
    * **merge**: when that keypoint already observes another point, the two points become one if
      their tracks see no image in common and every observation of both reprojects within
      ``complete_max_error_px`` of their weighted mean.

    Completion and merging run after every registration and once more at the end; the tracks they
    change are ``model_track_of`` (``track_of`` itself is ``build_tracks``' and stays as it was).

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

    Returns the model (``poses``, ``registered``, ``points``, ``point_tracks``, ``observed``, and
    ``model_track_of`` ``(N,)``: the track of each keypoint after continuation, completion and
    merging, which ``point_tracks`` refer to), ``cameras``, ``points3d``, ``observations`` and
    ``registration_errors`` (per registered image: the linear and non-linear PnP RMS). Warns with
    each image that could not be registered and why. Corresponds to ``pycolmap.incremental_mapping``.

    Reference: Schönberger and Frahm, CVPR 2016, sections 3-4 (4.5: continue, merge and complete
    tracks); H&Z chapters 7 and 12; Triggs et al. (2000).
    """
    images = _images(images)
    keypoints = _keypoints(keypoints, len(images))
    track_of = _track_of(track_of, keypoints).copy()  # becomes model_track_of: continued, completed, merged
    K = check_intrinsics(K, images)
    unit = _unit_descriptors_of(descriptors, keypoints)
    trees = _keypoint_trees(keypoints, len(images)) if complete_tracks else {}
    sizes = np.array([[image.width, image.height] for image in images.images], dtype=np.float64)
    guided = dict(max_error_px=complete_max_error_px, max_descriptor_distance=max_descriptor_distance)
    continued = completed = merged = 0
    anchor, _ = _initial(initial_pair, len(images))
    model = _model_from(initial_poses, initial_registered, initial_points, initial_point_tracks, len(images), keypoints)
    num_tracks = int(track_of.max()) + 1 if len(track_of) and track_of.max() >= 0 else 0
    tried = np.zeros(num_tracks, dtype=np.int64)
    for _, _, p in [model.observations(keypoints, track_of)]:
        counts = np.bincount(p, minlength=len(model.points))
        tried[model.point_tracks] = counts
    order: list[int] = []
    linear_rms, nonlinear_rms, reasons = [], [], {}
    tri_before, tri_after, tri_counts = [], [], []
    ba_before, ba_after, ba_ok = [], [], True
    step = 0
    failures = np.zeros(len(images), dtype=np.int64)
    adjusted_at = int(model.registered.sum())
    while True:
        best, best_count = -1, 0
        for v in np.flatnonzero(~model.registered):
            if failures[v] >= 2:
                continue
            kp, _ = _correspondences_2d3d(model, keypoints, track_of, int(v))
            if len(kp) < min_correspondences:
                reasons[int(v)] = (f"sees only {len(kp)} reconstructed points through its tracks (at least "
                                   f"{min_correspondences} are needed for PnP)")
                continue
            if len(kp) > best_count:
                best, best_count = int(v), len(kp)
        if best < 0:
            break
        kp, point = _correspondences_2d3d(model, keypoints, track_of, best)
        X, x = model.points[point], keypoints.xy[kp]
        try:
            found = pnp_ransac(X, x, K[best], threshold_px=pnp_threshold_px, rng=rng)
            if found.inliers.sum() < min_correspondences:
                raise InvalidValue("points2d", f"only {int(found.inliers.sum())} PnP inliers")
        except InvalidValue as exc:
            failures[best] += 1
            reasons[best] = f"PnP failed: {exc.reason}"
            # try it again only once the model has grown
            continue
        inl = found.inliers
        R, t = refine_pnp(found.R, found.t, X[inl], x[inl], K[best], loss="huber", f_scale=1.0)
        errors_after = reprojection_errors(R, t, X[inl], x[inl], K[best])
        linear_rms.append(found.rms_px)
        nonlinear_rms.append(float(np.sqrt(np.mean(errors_after**2))))
        model.poses[best] = _poses_matrix(R, t)
        model.registered[best] = True
        model.observed[kp[~inl]] = False
        if complete_tracks:
            continued += _continue_tracks(model, K, keypoints, track_of, best, max_error_px=complete_max_error_px)
        order.append(best)
        reasons.pop(best, None)
        failures[:] = 0
        added, before, after = _triangulate_new(model, K, keypoints, track_of, tried, min_angle_deg=min_angle_deg,
                                                max_error_px=max_error_px,
                                                min_track_length=2 if complete_tracks or not ignore_two_view_tracks
                                                else 3)
        if added:
            tri_before.append((before, added))
            tri_after.append((after, added))
        step += 1
        cameras, cloud, _ = _drawn(images, K, keypoints, model, track_of)
        yield Progress(step, None, nonlinear_rms[-1], f"registered {images.names[best]} (image {best}): "
                                                      f"{int(inl.sum())} PnP inliers, {added} new points",
                       values={"cameras": cameras, "points3d": cloud})
        if ba_iterations > 0 and model.registered.sum() >= ba_growth * adjusted_at:
            adjusted_at = int(model.registered.sum())
            bundle = _bundle(model, K, keypoints, track_of, anchor, loss=ba_loss, f_scale=1.0,
                             max_iterations=ba_iterations)
            while True:
                try:
                    iteration, rms = next(bundle)
                except StopIteration as stop:
                    result = stop.value[0]
                    break
                step += 1
                yield Progress(step, None, rms, f"bundle adjustment after image {best}: iteration {iteration}")
            ba_before.append(result.rms_before)
            ba_after.append(result.rms_after)
            ba_ok &= result.rms_after <= result.rms_before
        if complete_tracks:
            added, joined = _complete_and_merge(model, K, keypoints, track_of, unit, trees, sizes, **guided)
            completed, merged = completed + added, merged + joined
            if ignore_two_view_tracks:
                _drop_two_view_points(model, track_of, tried)
        _reject_outliers(model, K, keypoints, track_of, max_error_px)
    if complete_tracks and order:
        added, joined = _complete_and_merge(model, K, keypoints, track_of, unit, trees, sizes, rounds=3, **guided)
        completed, merged = completed + added, merged + joined
        if ignore_two_view_tracks:
            _drop_two_view_points(model, track_of, tried)
        _reject_outliers(model, K, keypoints, track_of, max_error_px)
    if len(order) == 0 and not model.registered.all():
        names = "; ".join(f"{images.names[v]} (image {v}): {reasons.get(int(v), 'not connected')}"
                          for v in np.flatnonzero(~model.registered))
        raise RegistrationFailed("images", f"no image could be registered beyond the initial pair: {names}")
    warnings = tuple(f"{images.names[v]} (image {v}) could not be registered: "
                     f"{reasons.get(int(v), 'it shares no verified tracks with the registered images')}"
                     for v in np.flatnonzero(~model.registered))
    cameras, cloud, observations = _drawn(images, K, keypoints, model, track_of)
    labels = tuple(images.names[v] for v in order)
    chart = Curve(np.arange(len(order), dtype=np.float64),
                  np.array([linear_rms, nonlinear_rms], dtype=np.float64).reshape(2, -1), kind="bar",
                  title="PnP reprojection RMS per registered image", xlabel="image", ylabel="RMS (px)",
                  labels=("linear PnP (DLT in RANSAC)", "non-linear PnP"), categories=labels)
    counts = np.bincount(observations.ids, minlength=len(model.points)) if len(observations) else np.zeros(0)

    def weighted(values):
        total = sum(n for _, n in values)
        return float(np.sqrt(sum(r * r * n for r, n in values) / total)) if total else 0.0

    return IncrementalModel(
        model.poses, model.registered, model.points, model.point_tracks, model.observed, track_of, cameras, cloud,
        observations, chart, warnings, int(model.registered.sum()), len(model.points),
        float(counts.mean()) if len(counts) else 0.0, continued, completed, merged,
        float(np.mean(linear_rms)) if linear_rms else 0.0, float(np.mean(nonlinear_rms)) if nonlinear_rms else 0.0,
        weighted(tri_before), weighted(tri_after), ba_before[-1] if ba_before else 0.0,
        ba_after[-1] if ba_after else 0.0, bool(ba_ok))


# ----------------------------------------------------------------------------------------------------
# 7. Filtering
# ----------------------------------------------------------------------------------------------------
@step_result
class FilteredModel:
    """Result of :func:`filter_points`."""

    filtered_points: np.ndarray
    filtered_point_tracks: np.ndarray
    filtered_observed: np.ndarray
    points3d: PointCloud
    observations: Points2D
    removed_observations: int = metric("observations removed (reprojection error too large)")
    removed_points: int = metric("points removed (fewer than two observations left, or too small an angle)")
    points_total: int = metric("points kept")


def _error_colors(errors: np.ndarray, scale: float) -> np.ndarray:
    """Green (0 px) to red (``scale`` px and more), ``(N, 3)``."""
    s = np.clip(np.asarray(errors, dtype=np.float64) / max(scale, 1e-9), 0.0, 1.0)[:, None]
    return (1 - s) * np.array([0.1, 0.8, 0.2]) + s * np.array([0.9, 0.1, 0.1])


def filter_points(images: ImageSet, keypoints: Points2D, track_of: np.ndarray, K: np.ndarray, poses: np.ndarray,
                  registered: np.ndarray, points: np.ndarray, point_tracks: np.ndarray, observed: np.ndarray,
                  model_track_of: np.ndarray | None = None, *,
                  max_error_px: Annotated[float, Range(0.1, 50.0)] = 1.0,
                  min_angle_deg: Annotated[float, Range(0.0, 30.0)] = 1.5) -> FilteredModel:
    """Drop observations whose reprojection error exceeds ``max_error_px``, then points left with fewer
    than two observations or whose largest triangulation angle is below ``min_angle_deg``.

    Run before the final bundle adjustment, so that it fits clean observations. The default 1 px
    suits calibrated cameras and SIFT (errors of a few tenths of a pixel); with a guessed K, raise it
    (COLMAP's default is 4 px).

    Args:
        max_error_px: largest reprojection error of an observation kept, pixels.
        min_angle_deg: smallest largest-angle between two rays of a point kept, degrees.

    ``model_track_of`` (the tracks after :func:`reconstruct_incrementally` continued, completed and
    merged them) replaces ``track_of`` when present.

    Returns ``filtered_points``, ``filtered_point_tracks`` and ``filtered_observed`` (the
    observations still used). Corresponds to COLMAP's ``FilterPoints`` (max reprojection error,
    min triangulation angle).

    Reference: Schönberger and Frahm (2016), section 4.5 (filtering).
    """
    images = _images(images)
    keypoints = _keypoints(keypoints, len(images))
    track_of = _model_tracks(track_of, model_track_of, keypoints)
    K = check_intrinsics(K, images)
    model = _model_from(poses, registered, points, point_tracks, len(images), keypoints, observed)
    kp, views, point = model.observations(keypoints, track_of)
    errors = _observation_errors(model, K, keypoints, kp, views, point)
    bad = errors > max_error_px
    model.observed[kp[bad]] = False
    views, point = views[~bad], point[~bad]
    counts = np.bincount(point, minlength=len(model.points))
    centers = -np.einsum("vji,vj->vi", model.poses[:, :, :3], model.poses[:, :, 3])
    mask = np.zeros((len(images), len(model.points)), dtype=bool)
    mask[views, point] = True
    angles = _ray_angles_deg(centers, model.points, mask) if len(model.points) else np.zeros(0)
    keep = (counts >= 2) & (angles >= min_angle_deg)
    before = len(model.points)
    model.points, model.point_tracks = model.points[keep], model.point_tracks[keep]
    if not len(model.points):
        raise StepFailed("filter_points", f"no point has two observations within {max_error_px:g} px and an angle of "
                                          f"{min_angle_deg:g} degrees; loosen the limits")
    _, cloud, observations = _drawn(images, K, keypoints, model, track_of)
    return FilteredModel(model.points, model.point_tracks, model.observed, cloud, observations, int(bad.sum()),
                         before - int(keep.sum()), len(model.points))


# ----------------------------------------------------------------------------------------------------
# 8. Final bundle adjustment
# ----------------------------------------------------------------------------------------------------
@step_result
class AdjustedModel:
    """Result of :func:`bundle_adjust_all`."""

    adjusted_poses: np.ndarray
    adjusted_K: np.ndarray
    adjusted_points: np.ndarray
    point_errors: np.ndarray
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


def bundle_adjust_all(images: ImageSet, keypoints: Points2D, track_of: np.ndarray, K: np.ndarray,
                      initial_pair: np.ndarray, poses: np.ndarray, registered: np.ndarray, filtered_points: np.ndarray,
                      filtered_point_tracks: np.ndarray, filtered_observed: np.ndarray,
                      model_track_of: np.ndarray | None = None, *,
                      loss: Literal["linear", "huber", "soft_l1", "cauchy", "arctan"] = "huber",
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
    ``model_track_of`` (the incremental step's tracks) replaces ``track_of`` when present.

    Args:
        loss: robust loss ("linear" is plain least squares).
        f_scale: residual size (px) beyond which the robust loss down-weights.
        refine_intrinsics: also refine fx, fy, cx, cy (one K when all views share it).
        max_iterations: most trust-region iterations.

    Returns ``adjusted_poses``, ``adjusted_K``, ``adjusted_points``, each point's mean reprojection
    error ``point_errors``, ``cameras`` tinted by their mean error (green 0 px to red 2 px),
    ``points3d``, ``observations`` and ``ba_cost`` (RMS per iteration). Corresponds to
    ``pycolmap.bundle_adjustment`` (Ceres).

    Reference: Triggs, McLauchlan, Hartley and Fitzgibbon, "Bundle adjustment - a modern synthesis"
    (2000); H&Z appendix A6.3; Schönberger and Frahm (2016), section 4.5.
    """
    images = _images(images)
    keypoints = _keypoints(keypoints, len(images))
    track_of = _model_tracks(track_of, model_track_of, keypoints)
    K = check_intrinsics(K, images)
    anchor, _ = _initial(initial_pair, len(images))
    model = _model_from(poses, registered, filtered_points, filtered_point_tracks, len(images), keypoints,
                        filtered_observed)
    if not model.registered[anchor]:
        anchor = int(np.flatnonzero(model.registered)[0])
    bundle = _bundle(model, K, keypoints, track_of, anchor, loss=loss, f_scale=f_scale,
                     max_iterations=max_iterations, refine_intrinsics=refine_intrinsics)
    while True:
        try:
            iteration, rms = next(bundle)
        except StopIteration as stop:
            result, cams, K_sub = stop.value
            break
        yield Progress(iteration, max_iterations, rms, "bundle adjustment")
    K_out = K.copy()
    K_out[cams] = K_sub
    kp, views, point = model.observations(keypoints, track_of)
    errors = _observation_errors(model, K_out, keypoints, kp, views, point)
    counts = np.bincount(point, minlength=len(model.points))
    point_errors = np.bincount(point, weights=errors, minlength=len(model.points)) / np.maximum(counts, 1)
    per_camera = np.array([errors[views == v].mean() if np.any(views == v) else 0.0
                           for v in np.flatnonzero(model.registered)])
    _, cloud, observations = _drawn(images, K_out, keypoints, model, track_of)
    cameras = _registered_cameras(images, K_out, model.poses, model.registered, colors=_error_colors(per_camera, 2.0))
    history = np.asarray(result.cost_history, dtype=np.float64)
    cost = Curve(np.arange(len(history), dtype=np.float64), history, title="Bundle adjustment", xlabel="iteration",
                 ylabel="RMS reprojection error (px)", labels=("RMS",))
    return AdjustedModel(model.poses, K_out, model.points, point_errors, cameras, cloud, observations, cost,
                         result.rms_before, result.rms_after, int(result.iterations), bool(result.improved),
                         int(model.registered.sum()), len(model.points), float(counts.mean()),
                         float(errors.mean()) if len(errors) else 0.0)


# ----------------------------------------------------------------------------------------------------
# Comparing with ground truth: a similarity alignment, then pose errors
# ----------------------------------------------------------------------------------------------------
def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``target ~ s Q source + d`` of least squared error (Umeyama 1991): ``(s, Q (3, 3), d (3,))``.

    Centre both sets, ``Sigma = T_c^T S_c / n``, ``U D V^T = svd(Sigma)``, ``Q = U diag(1, 1, det(U V^T)) V^T``,
    ``s = trace(diag(D) diag(1, 1, +-1)) / var(S)``, ``d = mean(T) - s Q mean(S)``. Corresponds to
    scikit-image's ``SimilarityTransform.estimate`` (which calls ``_umeyama``).

    Reference: S. Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", TPAMI 13(4), 1991.
    """
    S = np.asarray(source, dtype=np.float64)
    T = np.asarray(target, dtype=np.float64)
    ms, mt = S.mean(axis=0), T.mean(axis=0)
    Sc, Tc = S - ms, T - mt
    sigma = Tc.T @ Sc / len(S)
    U, D, Vt = np.linalg.svd(sigma)
    sign = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        sign[2] = -1.0
    Q = U @ np.diag(sign) @ Vt
    variance = np.mean(np.sum(Sc**2, axis=1))
    s = float(np.sum(D * sign) / variance) if variance > 0 else 1.0
    return s, Q, mt - s * Q @ ms


def align_poses(R_est: np.ndarray, t_est: np.ndarray, R_true: np.ndarray, t_true: np.ndarray):
    """Map estimated cameras into the true world by a similarity: returns ``(R_aligned, centers_aligned)``.

    Umeyama on the camera centres when they span a plane or a volume; on a line (a forward path) the
    rotation about the line is not determined by the centres, so the rotation is the chordal mean
    of ``R_true_i^T R_est_i`` and the scale and offset come from the centres by least squares.
    """
    C_est = -np.einsum("nji,nj->ni", R_est, t_est)
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    spread = np.linalg.svd(C_true - C_true.mean(axis=0), compute_uv=False)
    if len(C_true) >= 3 and spread[1] > 1e-3 * max(spread[0], 1e-12):
        s, Q, d = umeyama(C_est, C_true)
    else:
        Q = nearest_rotation(np.sum(np.swapaxes(R_true, 1, 2) @ R_est, axis=0))
        a = (C_est - C_est.mean(axis=0)) @ Q.T
        b = C_true - C_true.mean(axis=0)
        s = float(np.sum(a * b) / max(np.sum(a * a), 1e-300))
        d = C_true.mean(axis=0) - s * Q @ C_est.mean(axis=0)
    return R_est @ Q.T, s * C_est @ Q.T + d


def pose_errors(R_est: np.ndarray, t_est: np.ndarray, R_true: np.ndarray, t_true: np.ndarray,
                scene_size: float) -> dict[str, float]:
    """Rotation error (deg) and camera-centre error (fraction of ``scene_size``) after :func:`align_poses`."""
    R_aligned, C_aligned = align_poses(R_est, t_est, R_true, t_true)
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    rotation = rotation_angle_deg(R_aligned, R_true)
    center = np.linalg.norm(C_aligned - C_true, axis=1) / max(float(scene_size), 1e-12)
    return {"rotation_error_deg": float(rotation.mean()), "rotation_error_max_deg": float(rotation.max()),
            "center_error_rel": float(center.mean()), "center_error_max_rel": float(center.max())}


def _evaluate_with(poses_name: str, registered_name: str = "registered"):
    def evaluate(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
        if not truth or "R" not in truth or poses_name not in state or registered_name not in state:
            return {}
        reg = np.flatnonzero(state[registered_name])
        poses = state[poses_name]
        if len(reg) < 2:
            return {}
        return pose_errors(poses[reg, :, :3], poses[reg, :, 3], truth["R"][reg], truth["t"][reg],
                           truth.get("scene_size", 1.0))

    evaluate.__name__ = f"evaluate_{poses_name}"
    return evaluate


def evaluate_initial(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Rotation and direction-of-translation error of the initial pair against the truth."""
    if not truth or "R" not in truth or "initial_pose" not in state:
        return {}
    a, b = (int(v) for v in state["initial_pair"])
    R_rel = truth["R"][b] @ truth["R"][a].T
    t_rel = truth["t"][b] - R_rel @ truth["t"][a]
    pose = state["initial_pose"]
    cosine = float(pose[:, 3] @ t_rel / (np.linalg.norm(pose[:, 3]) * np.linalg.norm(t_rel)))
    return {"rotation_error_deg": float(rotation_angle_deg(pose[:, :3], R_rel)),
            "translation_direction_error_deg": float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))}


# ----------------------------------------------------------------------------------------------------
# Export
# ----------------------------------------------------------------------------------------------------
def reconstruction_from_state(state: dict[str, Any]):
    """The session's reconstruction as a :class:`lab.data.reconstruction.Reconstruction` (for COLMAP, PLY ...).

    Uses the most refined stage present: bundle-adjusted, else filtered, else incremental, else the
    two-view model. Only registered images are exported; keypoint indices are per image.
    """
    from lab.data.reconstruction import Reconstruction

    images: ImageSet = _images(state.get("images"))
    keypoints = _keypoints(state.get("keypoints"), len(images))
    track_of = _track_of(state.get("track_of"), keypoints)
    if "model_track_of" in state and "points" in state:  # every stage after the incremental one
        track_of = _track_of(state["model_track_of"], keypoints)
    K = np.asarray(state["K"], dtype=np.float64)
    if "adjusted_points" in state:
        model = _model_from(state["adjusted_poses"], state["registered"], state["adjusted_points"],
                            state["filtered_point_tracks"], len(images), keypoints, state["filtered_observed"])
        K = state["adjusted_K"]
    elif "filtered_points" in state:
        model = _model_from(state["poses"], state["registered"], state["filtered_points"],
                            state["filtered_point_tracks"], len(images), keypoints, state["filtered_observed"])
    elif "points" in state:
        model = _model_from(state["poses"], state["registered"], state["points"], state["point_tracks"], len(images),
                            keypoints, state["observed"])
    elif "initial_points" in state:
        model = _model_from(state["initial_poses"], state["initial_registered"], state["initial_points"],
                            state["initial_point_tracks"], len(images), keypoints)
    else:
        raise InvalidValue("state", "no reconstruction yet: run refine_initial_points or a later step first")
    K = np.asarray(K, dtype=np.float64)
    reg = np.flatnonzero(model.registered)
    new_index = np.full(len(images), -1)
    new_index[reg] = np.arange(len(reg))
    offsets = np.concatenate([[0], np.cumsum(np.bincount(keypoints.view, minlength=len(images)))])
    order = np.argsort(keypoints.view, kind="stable")
    local = np.empty(len(keypoints), dtype=np.int64)
    local[order] = np.arange(len(keypoints)) - offsets[keypoints.view[order]]
    kp, views, point = model.observations(keypoints, track_of)
    errors = _observation_errors(model, K, keypoints, kp, views, point)
    sort = np.lexsort((views, point))
    kp, views, point, errors = kp[sort], views[sort], point[sort], errors[sort]
    bounds = np.searchsorted(point, np.arange(len(model.points) + 1))
    tracks = tuple(np.column_stack([new_index[views[s:e]], local[kp[s:e]]]) for s, e in zip(bounds[:-1], bounds[1:]))
    point_errors = np.array([errors[s:e].mean() if e > s else 0.0 for s, e in zip(bounds[:-1], bounds[1:])])
    colors = np.round(255 * np.clip(_point_colors(images, keypoints, model, track_of), 0, 1)).astype(np.uint8)
    names = []
    for v in reg:
        name = "".join(c if not c.isspace() else "_" for c in (images[v].name or f"image_{v:03d}.png"))
        names.append(name if name not in names else f"{v:03d}_{name}")
    xy_by_view = [keypoints.xy[order[offsets[v]:offsets[v + 1]]] for v in reg]
    return Reconstruction(K=K[reg], sizes=np.array([[images[v].width, images[v].height] for v in reg]),
                          R=model.poses[reg, :, :3], t=model.poses[reg, :, 3], names=tuple(names),
                          keypoints=tuple(xy_by_view), xyz=model.points, colors=colors,
                          errors=np.where(np.isfinite(point_errors), point_errors, 0.0), tracks=tracks)


PIPELINE = Pipeline.build(
    name="sfm",
    title="Structure from motion",
    summary="Many photos in, cameras and a sparse point cloud out: features and matches for all pairs, geometric "
            "verification and the view graph, the initial pair and its pose from E, linear and non-linear "
            "triangulation, then register -> triangulate -> bundle adjust one image at a time, a final bundle "
            "adjustment and filtering.",
    steps=[detect_all_features, match_all_pairs, verify_pairs, build_tracks, choose_initial_pair, initialize_pose,
           triangulate_initial, refine_initial_points, reconstruct_incrementally, filter_points, bundle_adjust_all],
    datasets=[rendered, photos, match_files],
    evaluations={"initialize_pose": evaluate_initial,
                 "refine_initial_points": _evaluate_with("initial_poses", "initial_registered"),
                 "reconstruct_incrementally": _evaluate_with("poses"),
                 "bundle_adjust_all": _evaluate_with("adjusted_poses")},
)

__all__ = ["PIPELINE", "RegistrationFailed", "detect_all_features", "match_all_pairs", "image_pairs", "verify_pairs",
           "build_tracks", "split_inconsistent", "unit_descriptors", "choose_initial_pair", "initialize_pose",
           "triangulate_initial", "refine_initial_points", "reconstruct_incrementally", "filter_points",
           "bundle_adjust_all", "umeyama", "align_poses", "pose_errors", "reconstruction_from_state"]
