"""The stereo pipeline's steps, in order: rectify, match, aggregate, pick, check, refine, filter, triangulate.

Each step checks its inputs, then does what its docstring says; the math it calls is in the
package's topic files (:mod:`.costs`, :mod:`.sgm`, :mod:`.winners`, :mod:`.filters`,
:mod:`.rectify`, :mod:`.depth`), their loops in :mod:`._kernels`. The state names each step reads
and writes are listed in :mod:`lab.modules.stereo`.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np

from lab.core import (Cameras, Image, InvalidControl, InvalidValue, PointCloud, Points2D, Range, Warnings,
                      metric, step_result)
from lab.geometry.camera import as_intrinsics
from lab.geometry.rectification import StereoCalibration, stereo_rectify
from lab.geometry.rotations import rotation_angle_deg
from lab.modules.stereo._checks import (check_map, check_max_disparity, check_pair, check_volume,
                                        check_window, integer_disparity, volume_fits)
from lab.modules.stereo.costs import COSTS, Cost, census_costs, ncc_costs, nssd_costs, window_costs
from lab.modules.stereo.depth import depth_from_disparity, point_cloud, rectified_cameras
from lab.modules.stereo.disparity_range import estimate_max_disparity, match_range_features
from lab.modules.stereo.filters import (HOLE, colorize_disparity, fill_holes, median_filter, remove_peaks,
                                        unique_winners)
from lab.modules.stereo.lean import (CensusRows, RowWinners, block_matching_rows, census_rows, check_by_rows,
                                     semi_global_matching_rows)
from lab.modules.stereo.rectify import check_rows, remap_pair, row_misalignment
from lab.modules.stereo.sgm import semi_global_matching
from lab.modules.stereo.winners import check_winners, costs_around, right_disparity


# ----------------------------------------------------------------------------------------------------
# 1. Rectification
# ----------------------------------------------------------------------------------------------------
@step_result
class RectifiedPair:
    """Result of :func:`rectify_pair`."""

    left: Image
    right: Image
    K: np.ndarray
    baseline: float
    disparity_offset: float
    warnings: Warnings
    focal_px: float = metric("focal length of the rectified cameras", unit="px")
    baseline_m: float = metric("distance between the camera centres", unit="m")
    left_rotation_deg: float = metric("rotation of the left camera by rectification", unit="deg")
    right_rotation_deg: float = metric("rotation of the right camera by rectification", unit="deg")
    row_error_px: float = metric("largest vertical offset between the rows of the pair, fitted to matched "
                                 "ORB features (-1: too few features)", unit="px")
    resampled: bool = metric("the images were resampled (False: the pair was rectified already)")


def rectify_pair(left_raw: Image, right_raw: Image, calibration: StereoCalibration, *,
                 max_row_error: Annotated[float, Range(0.1, 100.0)] = 1.0) -> RectifiedPair:
    """Turn both cameras so that epipolar lines become image rows, and resample the photos.

    The rectifying rotations and the common camera matrix come from Bouguet's algorithm
    (:func:`lab.geometry.rectification.stereo_rectify`, ``cv2.stereoRectify`` with zero disparity
    at infinity); every pixel of each rectified image is mapped back through the rotation and the
    lens distortion to the photo (:func:`lab.geometry.rectification.rectification_map`, as
    ``cv2.initUndistortRectifyMap``) and sampled bilinearly (``cv2.remap``, black outside).

    A pair whose calibration says it is rectified already (no rotation between the cameras, the
    right one straight to the right, no distortion, one focal length and ``cy``) passes through
    unchanged, keeping the difference of the principal points as ``disparity_offset`` (Middlebury's
    ``doffs``): then matched ORB features must share their rows (:func:`row_misalignment`), else
    the step refuses the pair.

    Args:
        max_row_error: largest vertical offset (pixels) between the rows of a pair declared
            rectified, as fitted to matched features.

    Returns ``left``, ``right`` (rectified Images), ``K`` (3, 3), ``baseline`` (metres) and
    ``disparity_offset`` (pixels, ``Z = f B / (d + disparity_offset)``).

    Reference: J.-Y. Bouguet, Camera Calibration Toolbox for Matlab; Hartley & Zisserman (2nd ed.),
    section 11.12; A. Fusiello et al., MVA 12 (2000).
    """
    left_raw, right_raw = check_pair(left_raw, right_raw, names=("left_raw", "right_raw"))
    if not isinstance(calibration, StereoCalibration):
        raise InvalidValue("calibration", f"expected a StereoCalibration, got {type(calibration).__name__}")
    if calibration.is_rectified():
        error, warnings = check_rows(left_raw, right_raw, max_row_error)
        K = calibration.K_left
        return RectifiedPair(left=left_raw, right=right_raw, K=K.copy(), baseline=calibration.baseline,
                             disparity_offset=float(calibration.K_right[0, 2] - K[0, 2]), warnings=warnings,
                             focal_px=float(K[0, 0]), baseline_m=calibration.baseline, left_rotation_deg=0.0,
                             right_rotation_deg=0.0, row_error_px=error, resampled=False)
    rect = stereo_rectify(calibration.K_left, calibration.dist_left, calibration.K_right,
                          calibration.dist_right, (left_raw.width, left_raw.height), calibration.R,
                          calibration.T)
    if rect.vertical:
        raise InvalidValue("calibration", "the cameras are stacked vertically (the baseline is mostly "
                                          "along y); rotate both photos by 90 degrees so that the baseline "
                                          "runs along the rows")
    left, right = remap_pair(left_raw, right_raw, calibration, rect)
    error, _ = row_misalignment(left, right)
    return RectifiedPair(left=left, right=right, K=rect.K, baseline=rect.baseline,
                         disparity_offset=rect.disparity_offset, warnings=(), focal_px=float(rect.K[0, 0]),
                         baseline_m=rect.baseline,
                         left_rotation_deg=float(rotation_angle_deg(np.eye(3), rect.R_left)),
                         right_rotation_deg=float(rotation_angle_deg(np.eye(3), rect.R_right)),
                         row_error_px=error, resampled=True)


# ----------------------------------------------------------------------------------------------------
# 2. The disparity range, from matched features
# ----------------------------------------------------------------------------------------------------
@step_result
class DisparityRange:
    """Result of :func:`estimate_disparity_range`."""

    disparity_features: Points2D
    disparity_features_right: Points2D
    warnings: Warnings
    auto_max_disparity: int = metric("largest disparity that max_disparity = 0 (auto) searches (-1: no "
                                     "estimate)", unit="px")
    range_matches: int = metric("SIFT features matched along the rows")
    feature_disparity_low: float = metric("1st percentile of the matched features' disparities", unit="px")
    feature_disparity_high: float = metric("99th percentile of the matched features' disparities", unit="px")


def estimate_disparity_range(left: Image, right: Image) -> DisparityRange:
    """How far apart the two views of a point are, from sparse matched features: the range to search.

    SIFT keypoints of both images are matched by descriptor with Lowe's ratio test and kept when
    they lie on one row (the rectified pair's constraint) at a disparity ``x_left - x_right >= 0``;
    the 99th percentile of their disparities plus a margin (8 px and 5 %), rounded up to a multiple
    of 16, is ``auto_max_disparity``, what :func:`cost_volume` searches with ``max_disparity = 0``
    (auto; :mod:`.disparity_range`). The matched features are drawn on both images, coloured by
    their disparity (turbo, as the disparity map). With fewer than 10 matches there is no estimate
    (-1, and a warning saying to set ``max_disparity``).

    Reference: D. Lowe, IJCV 60 (2004), section 7.1 (the ratio test); Hartley & Zisserman (2nd ed.),
    section 11.12 (corresponding points of a rectified pair share their row).
    """
    left, right = check_pair(left, right)
    matches = match_range_features(left, right)
    top, note = estimate_max_disparity(matches, left.width)
    d = matches.disparity
    scale = float(top) if top > 0 else float(d.max()) if len(d) else 1.0
    colors = colorize_disparity(d[None, :], max_disparity=scale).pixels[0].astype(np.float64) if len(d) \
        else np.zeros((0, 3))
    ids = np.arange(len(d))
    return DisparityRange(
        disparity_features=Points2D(matches.left, ids=ids, colors=colors, image="left"),
        disparity_features_right=Points2D(matches.right, ids=ids, colors=colors, image="right"),
        warnings=(note,) if top < 0 else (), auto_max_disparity=top, range_matches=len(d),
        feature_disparity_low=float(np.percentile(d, 1.0)) if len(d) else -1.0,
        feature_disparity_high=float(np.percentile(d, 99.0)) if len(d) else -1.0)


def resolve_max_disparity(left: Image, right: Image, max_disparity: int) -> int:
    """``max_disparity``, or with 0 (auto) the range :func:`estimate_disparity_range` estimates (an error
    naming ``max_disparity`` when the features give none)."""
    if int(max_disparity) != 0:
        return check_max_disparity(max_disparity, left.width)
    top, note = estimate_max_disparity(match_range_features(left, right), left.width)
    if top < 0:
        raise InvalidControl("max_disparity", f"0 (auto) estimates the range from matched features, "
                                              f"but {note}")
    return check_max_disparity(top, left.width)


# ----------------------------------------------------------------------------------------------------
# 3. Matching costs
# ----------------------------------------------------------------------------------------------------
def cost_volume(left: Image, right: Image, *, cost: Cost = "census",
                window: Annotated[int, Range(1, 31)] = 5,
                max_disparity: Annotated[int, Range(0, 1024)] = 0,
                ) -> Annotated[np.ndarray | CensusRows, "cost_volume"]:
    """The matching cost of every left pixel at every disparity, aggregated over a square window.

    With ``a`` the left window around ``(x, y)`` and ``b`` the right window around ``(x - d, y)``
    (gray levels in [0, 1], ``n = window^2`` pixels, borders replicated), the costs are
    (Scharstein and Szeliski 2002, section 3.1; Szeliski 2022, section 12.3):

    - ``ssd``: ``(1/n) sum (a - b)^2``, sum of squared differences (``cv2.matchTemplate``'s
      TM_SQDIFF divided by n);
    - ``nssd``: normalized SSD ``sum (a - b)^2 / sqrt(sum a^2 sum b^2)`` (TM_SQDIFF_NORMED);
    - ``sad``: ``(1/n) sum |a - b|``, sum of absolute differences;
    - ``zsad``: zero-mean SAD, ``(1/n) sum |a' - b'|`` on images whose local mean (over the
      window around each pixel) is subtracted, so that a brightness offset between the cameras
      costs nothing; subtracting each window's own mean instead would not be a box filter;
    - ``ncc``: ``1 - NCC``, NCC the zero-mean normalized cross-correlation
      ``sum (a - mean a)(b - mean b) / sqrt(sum (a - mean a)^2 sum (b - mean b)^2)``
      (TM_CCOEFF_NORMED), 1 where a window is flat (its gray-level variance below
      :data:`NCC_FLAT_VARIANCE`); its window moments are float64 (:func:`ncc_costs`);
    - ``rank``: ``(1/n) sum |r_a - r_b| / (n - 1)``, ``r`` the rank transform over the window
      (Zabih and Woodfill 1994);
    - ``census``: ``(1/n) sum hamming(c_a, c_b) / (n - 1)``, ``c`` the census bit strings over
      the window (Zabih and Woodfill 1994).

    Every sum over a window is a box filter of a per-pixel term (or product) applied to each
    disparity slice, computed with running sums in O(1) per window (:func:`box_mean`), never by
    a loop over the window's pixels; census sums its Hamming distances in one fused kernel
    (:func:`census_costs`). Color images are matched in gray.

    Args:
        cost: the matching cost.
        window: side of the square window in pixels (odd; at least 3 for rank and census).
        max_disparity: largest disparity searched (pixels); the volume holds ``max_disparity + 1``.
            0: estimated from matched features (:func:`estimate_disparity_range`'s auto_max_disparity).

    Returns ``(H, W, max_disparity + 1)`` float32, ``volume[y, x, d]`` the cost of matching left
    pixel ``(x, y)`` with right pixel ``(x - d, y)`` (LESSON TASK).

    Full resolution: a volume of more than :data:`~lab.modules.stereo.MAX_VOLUME_ENTRIES` costs is not
    built. Census costs are then returned as a :class:`~lab.modules.stereo.lean.CensusRows` (the census
    strings, which compute any band of rows of the same volume on demand), and :func:`aggregate_costs`
    aggregates them by rows in bounded memory (:mod:`.lean`; at most
    :data:`lab.core.budgets.MAX_STEREO_BYTES`, else refused naming the memory needed and the
    dataset's downsample option); other costs are refused there.

    Reference: Scharstein and Szeliski (2002), sections 3.1-3.2; Zabih and Woodfill (1994).
    """
    left, right = check_pair(left, right)
    if cost not in COSTS:
        raise InvalidControl("cost", f"must be one of {list(COSTS)}, got {cost!r}")
    window = check_window(window, cost)
    max_disparity = resolve_max_disparity(left, right, max_disparity)
    disparities = max_disparity + 1
    a, b = left.gray(), right.gray()
    if not volume_fits(left.height, left.width, disparities):
        check_by_rows(cost, left.height, left.width, disparities, window)
        return census_rows(a, b, disparities, window)
    if cost == "census":
        return census_costs(a, b, disparities, window)
    if cost == "ncc":
        return ncc_costs(a, b, disparities, window)
    if cost == "nssd":
        return nssd_costs(a, b, disparities, window)
    return window_costs(cost, a, b, disparities, window)  # ssd, sad, zsad, rank


# ----------------------------------------------------------------------------------------------------
# 3. Aggregation
# ----------------------------------------------------------------------------------------------------
def aggregate_costs(cost_volume: np.ndarray | CensusRows, *, method: Literal["sgm", "none"] = "sgm",
                    P1: Annotated[float, Range(0.0, 10.0)] = 0.05,
                    P2: Annotated[float, Range(0.0, 100.0)] = 1.0,
                    paths: Literal[4, 8] = 8) -> Annotated[np.ndarray | RowWinners, "aggregated_cost"]:
    """Semi-global matching: add to every cost the cheapest way to reach it along 4 or 8 straight paths.

    Along each direction ``r`` (Hirschmüller 2008, equation 13)::

        L_r(p, d) = C(p, d) + min(L_r(p - r, d), L_r(p - r, d +- 1) + P1, min_k L_r(p - r, k) + P2)
                    - min_k L_r(p - r, k)

    so a change of one pixel in disparity between neighbours costs ``P1`` and a larger jump
    ``P2``; ``S(p, d) = sum_r L_r(p, d)`` approximates a 2D smoothness energy by 1D dynamic
    programs. ``method = "none"`` passes the window costs through (block matching).

    Args:
        method: "sgm" (semi-global matching) or "none" (block matching: the window is the only
            aggregation).
        P1: penalty for a disparity change of one pixel, in cost units (the normalized costs of
            :func:`cost_volume` are about 0.5 for a mismatch).
        P2: penalty for a larger disparity change (at least P1).
        paths: 4 (horizontal and vertical) or 8 (and the diagonals).

    Returns ``(H, W, D)`` float32 aggregated costs. Corresponds to the aggregation inside
    ``cv2.StereoSGBM`` (which adds Birchfield-Tomasi costs and its own post-processing). A volume
    too large to keep (a :class:`~lab.modules.stereo.lean.CensusRows`) is aggregated by rows in bounded
    memory and returned as its :class:`~lab.modules.stereo.lean.RowWinners`, what the next steps read
    of it, equal to what they read of the full volume (:mod:`.lean`).

    Reference: H. Hirschmüller, TPAMI 30(2), 2008, sections 3.3 and 4.1.
    """
    if isinstance(cost_volume, CensusRows):
        if method == "none":
            return block_matching_rows(cost_volume)
        return semi_global_matching_rows(cost_volume, P1=P1, P2=P2, paths=int(paths))
    if method == "none":
        return check_volume(cost_volume, "cost_volume")
    return semi_global_matching(cost_volume, P1=P1, P2=P2, paths=int(paths))


# ----------------------------------------------------------------------------------------------------
# 4. Disparity selection, left-right check, sub-pixel refinement
# ----------------------------------------------------------------------------------------------------
def winner_take_all(aggregated_cost: np.ndarray) -> Annotated[np.ndarray, "disparity_wta"]:
    """Each pixel's disparity is the one with the lowest cost: ``d(p) = argmin_d S(p, d)`` (first on ties).

    Returns ``(H, W)`` int64 (LESSON TASK). Reference: Scharstein and Szeliski (2002), section 3.3.
    (A volume aggregated by rows, :class:`~lab.modules.stereo.lean.RowWinners`, carries its winners.)
    """
    if isinstance(aggregated_cost, RowWinners):
        return aggregated_cost.winner.copy()
    volume = check_volume(aggregated_cost, "aggregated_cost", finite=False)
    winner = np.argmin(volume, axis=2)
    check_winners(volume, winner)
    return winner


def left_right_check(aggregated_cost: np.ndarray, disparity_wta: np.ndarray, *,
                     max_difference: Annotated[int, Range(0, 16)] = 1) -> Annotated[np.ndarray, "consistent"]:
    """Keep a pixel when the right image's match points back to it:
    ``|d_L(x) - d_R(x - d_L(x))| <= max_difference``.

    ``d_R`` is the right image's winner-take-all disparity read from the same volume
    (:func:`right_disparity`). Occluded pixels (seen only by the left camera) and mismatches fail;
    so do pixels whose match falls left of the right image.

    Args:
        max_difference: largest disagreement (pixels) between the two disparities.

    Returns ``(H, W)`` bool, True where consistent (LESSON TASK). Corresponds to the
    ``disp12MaxDiff`` test of ``cv2.StereoSGBM``.

    Reference: Hirschmüller (2008), section 3.4 (equation 15); P. Fua, "A parallel stereo algorithm
    that produces dense depth maps and preserves image features", MVA 6 (1993).
    """
    if isinstance(aggregated_cost, RowWinners):
        (H, W, D), right = aggregated_cost.shape, aggregated_cost.right
    else:
        volume = check_volume(aggregated_cost, "aggregated_cost", finite=False)
        (H, W, D), right = volume.shape, right_disparity(volume)
    left = integer_disparity(disparity_wta, "disparity_wta", (H, W), D)
    columns = np.arange(W)[None, :] - left
    inside = columns >= 0
    back = right[np.arange(H)[:, None], np.clip(columns, 0, W - 1)]
    return inside & (np.abs(left - back) <= int(max_difference))


def refine_subpixel(aggregated_cost: np.ndarray | RowWinners, disparity_wta: np.ndarray, *,
                    method: Literal["parabola", "none"] = "parabola",
                    ) -> Annotated[np.ndarray, "disparity_subpixel"]:
    """Sub-pixel disparity from a parabola through the costs at ``d - 1``, ``d``, ``d + 1``.

    ``d* = d + (C(d - 1) - C(d + 1)) / (2 (C(d - 1) - 2 C(d) + C(d + 1)))``, the vertex, clipped to
    ``d +- 0.5``; kept at ``d`` at either end of the range or where the parabola does not open
    upwards. Returns ``(H, W)`` float64 for every pixel. Corresponds to the refinement inside
    ``cv2.StereoSGBM`` and ``cv2.StereoBM``.

    Args:
        method: "parabola" or "none" (integer disparities).

    Reference: Scharstein and Szeliski (2002), section 3.4; Hirschmüller (2008), section 3.3.
    """
    lean = isinstance(aggregated_cost, RowWinners)
    volume = aggregated_cost if lean else check_volume(aggregated_cost, "aggregated_cost", finite=False)
    H, W, D = volume.shape
    d = integer_disparity(disparity_wta, "disparity_wta", (H, W), D)
    out = d.astype(np.float64)
    if method == "none" or D < 3:
        return out
    inner = (d >= 1) & (d <= D - 2)
    c0, c1, c2 = around_winners(volume, d)
    curvature = c0 - 2.0 * c1 + c2
    usable = inner & (curvature > 0)
    offset = np.where(usable, (c0 - c2) / (2.0 * np.where(usable, curvature, 1.0)), 0.0)
    if not (np.all(np.isfinite(c1)) and np.all(np.isfinite(offset))):
        raise InvalidValue("aggregated_cost", "contains NaN or infinite costs")
    return out + np.clip(offset, -0.5, 0.5)


# ----------------------------------------------------------------------------------------------------
# 5. Filtering
# ----------------------------------------------------------------------------------------------------
def around_winners(volume: np.ndarray | RowWinners, winner: np.ndarray) -> np.ndarray:
    """``(3, H, W)``: the costs at ``d - 1, d, d + 1`` for ``d`` the ``winner`` clipped to ``[1, D - 2]``; a
    volume aggregated by rows keeps them for its own winners only."""
    D = volume.shape[2]
    if not isinstance(volume, RowWinners):
        return costs_around(volume, np.clip(winner, 1, D - 2))
    if not np.array_equal(winner, volume.winner):
        raise InvalidValue("disparity_wta", "a cost volume aggregated by rows (too large to keep) holds the "
                                            "costs around its own winners only: refine the disparities that "
                                            "winner_take_all picked from it")
    return volume.around


@step_result
class FilteredDisparity:
    """Result of :func:`filter_disparity`."""

    disparity: np.ndarray
    disparity_image: Image
    coverage: float = metric("fraction of pixels with a disparity")
    inconsistent: float = metric("fraction of pixels removed by the left-right check")
    ambiguous: float = metric("fraction of the remaining pixels removed by the uniqueness test")
    peaks: float = metric("fraction of pixels removed as small islands (peaks)")
    filled: float = metric("fraction of pixels filled by hole filling")


def filter_disparity(disparity_subpixel: np.ndarray, consistent: np.ndarray,
                     aggregated_cost: np.ndarray | RowWinners, *,
                     median: Literal[1, 3, 5] = 3, uniqueness: Annotated[float, Range(0.0, 0.9)] = 0.05,
                     speckle_size: Annotated[int, Range(0, 100000)] = 100,
                     speckle_range: Annotated[float, Range(0.0, 16.0)] = 2.0,
                     fill: bool = False) -> FilteredDisparity:
    """Clean the disparity map: median filter, drop inconsistent, ambiguous and isolated pixels, fill holes.

    In order: a ``median x median`` median filter of the refined disparities (Hirschmüller 2008,
    section 4.1); holes (-1) where the left-right check failed or where the winner is not unique
    (its cost is not below ``1 - uniqueness`` times the best cost two or more disparities away,
    OpenCV's ``uniquenessRatio``); small islands removed (:func:`remove_peaks`, OpenCV's
    ``speckleWindowSize``/``speckleRange``); then, with ``fill``, each hole takes the background
    disparity of its row (:func:`fill_holes`).

    Args:
        median: side of the median filter (1: none).
        uniqueness: margin by which the best cost must beat the second best (0: no test).
        speckle_size: largest island (pixels) removed as a peak (0: none).
        speckle_range: largest disparity step (pixels) inside one island.
        fill: fill the holes with the background disparity of their row.

    Returns ``disparity`` ``(H, W)`` float64 with -1 in holes and ``disparity_image``.
    """
    lean = isinstance(aggregated_cost, RowWinners)
    volume = aggregated_cost if lean else check_volume(aggregated_cost, "aggregated_cost", finite=False)
    H, W, D = volume.shape
    refined = check_map(disparity_subpixel, "disparity_subpixel", (H, W))
    mask = check_map(consistent, "consistent", (H, W), kind="b")
    if median not in (1, 3, 5):
        raise InvalidControl("median", f"must be 1, 3 or 5, got {median!r}")
    smoothed = median_filter(refined, median)
    keep = mask.copy()
    ambiguous = 0.0
    if uniqueness > 0:
        unique = unique_winners(volume, uniqueness)
        ambiguous = float(np.mean(keep & ~unique)) if keep.size else 0.0
        keep &= unique
    disparity = np.where(keep, np.maximum(smoothed, 0.0), HOLE)
    before_peaks = disparity >= 0
    disparity = remove_peaks(disparity, max_size=int(speckle_size), max_difference=float(speckle_range))
    peaks = float(np.mean(before_peaks & (disparity < 0)))
    filled = 0.0
    if fill:
        holes = disparity < 0
        disparity = fill_holes(disparity)
        filled = float(np.mean(holes & (disparity >= 0)))
    return FilteredDisparity(disparity=disparity,
                             disparity_image=colorize_disparity(disparity, max_disparity=D - 1),
                             coverage=float(np.mean(disparity >= 0)), inconsistent=float(np.mean(~mask)),
                             ambiguous=ambiguous, peaks=peaks, filled=filled)


# ----------------------------------------------------------------------------------------------------
# 6. Depth and points
# ----------------------------------------------------------------------------------------------------
@step_result
class DenseReconstruction:
    """Result of :func:`reconstruct_points`."""

    depth: np.ndarray
    depth_uncertainty: np.ndarray
    points3d: PointCloud
    cameras: Cameras
    points: int = metric("points in the cloud")
    median_depth_m: float = metric("median depth", unit="m")
    median_uncertainty_m: float = metric("median depth uncertainty", unit="m")


def reconstruct_points(disparity: np.ndarray, left: Image, K: np.ndarray, baseline: float,
                       disparity_offset: float, *,
                       disparity_std: Annotated[float, Range(0.0, 10.0)] = 0.5,
                       stride: Annotated[int, Range(1, 16)] = 2,
                       max_depth: Annotated[float, Range(0.0, 1e6)] = 0.0) -> DenseReconstruction:
    """Depth, its uncertainty and a coloured point cloud from the disparity map.

    ``Z = f B / (d + disparity_offset)`` (similar triangles of the rectified pair),
    ``u_z = Z^2 u_d / (f B)`` (depth gets uncertain with the square of distance), and
    ``X = Z K^-1 (x, y, 1)`` in the
    rectified left camera frame, coloured by the left image. ``cameras`` holds the rectified pair:
    the left camera at the origin, the right one ``baseline`` metres along x.

    Args:
        disparity_std: uncertainty ``u_d`` of a disparity (pixels).
        stride: keep every ``stride``-th pixel along rows and columns in the point cloud.
        max_depth: leave out points farther than this (metres; 0: keep all).

    Reference: Hartley & Zisserman (2nd ed.), section 11.12 (the rectified pair), section 5.2
    (propagation of uncertainty); Szeliski (2022), section 12.1.
    """
    if not isinstance(left, Image):
        raise InvalidValue("left", f"expected an Image, got {type(left).__name__}")
    d = check_map(disparity, "disparity", (left.height, left.width))
    K = as_intrinsics(K)
    depth, uncertainty = depth_from_disparity(d, K, baseline, disparity_offset=float(disparity_offset),
                                              disparity_std=disparity_std)
    points3d = point_cloud(depth, left, K, stride=int(stride), max_depth=max_depth)
    cameras = rectified_cameras(K, baseline, float(disparity_offset), left.width, left.height)
    valid = depth > 0
    median_depth = float(np.median(depth[valid])) if valid.any() else 0.0
    median_uncertainty = float(np.median(uncertainty[valid])) if valid.any() else 0.0
    return DenseReconstruction(depth=depth, depth_uncertainty=uncertainty, points3d=points3d, cameras=cameras,
                               points=len(points3d), median_depth_m=median_depth,
                               median_uncertainty_m=median_uncertainty)
