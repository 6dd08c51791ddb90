"""Stereo disparity step by step: rectify, match, aggregate (SGM), pick, check, refine, filter, triangulate.

References: D. Scharstein and R. Szeliski, "A taxonomy and evaluation of dense two-frame stereo
correspondence algorithms", IJCV 47 (2002) (the four stages: matching cost, aggregation,
optimization, refinement; the bad-pixel metrics); H. Hirschmüller, "Stereo processing by semiglobal
matching and mutual information", IEEE TPAMI 30(2), 2008 (SGM, the left-right check, peak removal,
hole interpolation); R. Zabih and J. Woodfill, "Non-parametric local transforms for computing visual
correspondence", ECCV 1994 (rank and census); R. Szeliski, *Computer Vision: Algorithms and
Applications*, 2nd ed. (2022), chapter 12 (dense correspondence); Hartley & Zisserman, *Multiple View
Geometry*, 2nd ed., section 11.12 (rectification); J.-Y. Bouguet's rectification
(:mod:`lab.geometry.rectification`).

Conventions. Images are rectified: a point at column ``x`` of the left image is seen at column
``x - d`` of the right one, on the same row, with disparity ``d >= 0`` (pixels). A cost volume is a
float32 array ``(H, W, D)``: ``volume[y, x, d]`` is the cost of matching left pixel ``(x, y)`` with
right pixel ``(x - d, y)``, for ``d = 0 .. max_disparity`` (``D = max_disparity + 1``); right pixels
left of the image take the value of its first column (border replicated), as do windows reaching
over any border. Costs are normalized per window pixel so that one penalty suits every cost and
window (:mod:`.costs`).

State names (float64 unless said):
    left_raw, right_raw   Image              the photos as taken (dataset)
    calibration           StereoCalibration  K, distortion, R, T of the pair (dataset)
    left, right           Image              the rectified pair
    K                     (3, 3)             camera matrix of the rectified left image
    baseline              float              distance between the camera centres, metres
    disparity_offset      float              cx_right - cx_left of the rectified pair, pixels
                                             (0 after our rectification; Middlebury's ``doffs``)
    disparity_features    Points2D           SIFT features matched along the rows, on ``left``, coloured by
                                             their disparity
    disparity_features_right  Points2D       the same features on ``right``
    cost_volume           (H, W, D) float32  matching costs (kept in state: at most 2**26 entries; a
                                             larger census volume is a CensusRows, its rows on demand)
    aggregated_cost       (H, W, D) float32  costs after aggregation (SGM), or the same array (a
                                             RowWinners of a volume aggregated by rows, :mod:`.lean`)
    disparity_wta         (H, W) int64       winner-take-all disparity of every pixel
    consistent            (H, W) bool        pixels that pass the left-right check
    disparity_subpixel    (H, W)             disparity refined by a parabola, every pixel
    disparity             (H, W)             final disparity in pixels; -1 marks a hole (no NaN)
    disparity_image       Image              the disparity colour-mapped (turbo), holes black
    depth                 (H, W)             Z = f B / (d + disparity_offset) in metres; 0 in holes
    depth_uncertainty     (H, W)             u_z = Z^2 u_d / (f B), metres; 0 in holes
    points3d              PointCloud         pixels with a depth, in the rectified left camera frame, coloured
    cameras               Cameras            the rectified pair (left at the origin, right at x = baseline)

Ground truth (``Session.truth``, never a step input): ``disparity`` (H, W) with -1 where unknown,
``depth`` (H, W) with 0 where unknown, ``points`` (N, 3) scene points in the left raw camera frame
(synthetic unrectified pairs, to measure rectification). :func:`error_map` and
:func:`cost_curves` build the viewer's error map and the cost curves of a clicked pixel.

The package, in reading order: :mod:`.steps` (the steps above, in pipeline order, with their
results); the math they call, by topic: :mod:`.costs` (matching costs, box filter, census),
:mod:`.sgm` (semi-global matching), :mod:`.winners` (winners of a volume), :mod:`.filters`,
:mod:`.rectify`, :mod:`.depth`, :mod:`.realtime` (SAD block matching at video rate); :mod:`.evaluate`
(comparisons with the truth, the viewer's error map and cost curves); :mod:`.datasets` (the pairs and
their truth). The Numba kernels are in the private :mod:`._kernels`; each fast function ``x`` has a
slow readable ``x_reference`` in :mod:`.reference`, the tests' oracle (naming as in
:mod:`lab.core.kernels`). This file is the only import surface.
"""

from __future__ import annotations

from lab.core import Pipeline
from lab.modules.stereo._checks import MAX_VOLUME_ENTRIES
from lab.modules.stereo.costs import (COSTS, NCC_FLAT_VARIANCE, Cost, box_mean, census_costs,
                                      census_transform, hamming_costs, rank_transform, shifted_right)
from lab.modules.stereo.datasets import (MOTORCYCLE_BASELINE_M, MOTORCYCLE_CENTRE_PX, MOTORCYCLE_DOFFS_PX,
                                         MOTORCYCLE_FOCAL_PX, folder, motorcycle, read_calibration,
                                         read_disparity, synthetic)
from lab.modules.stereo.depth import depth_from_disparity
from lab.modules.stereo.disparity_range import RangeMatches, estimate_max_disparity, match_range_features
from lab.modules.stereo.evaluate import (BAD_THRESHOLDS, cost_curves, disparity_errors, error_map,
                                         evaluate_depth, evaluate_disparity, evaluate_left_right,
                                         evaluate_rectification, evaluate_subpixel, evaluate_winner_take_all,
                                         volume_curve)
from lab.modules.stereo.filters import HOLE, colorize_disparity, fill_holes, remove_peaks
from lab.modules.stereo.lean import (CensusRows, RowWinners, block_matching_rows, census_rows,
                                     lean_memory_bytes, semi_global_matching_rows)
from lab.modules.stereo.realtime import block_match_realtime
from lab.modules.stereo.rectify import row_misalignment
from lab.modules.stereo.reference import (best_two_costs_reference, block_match_realtime_reference,
                                          box_mean_reference, census_transform_reference,
                                          hamming_costs_reference, right_disparity_reference, sgm_reference)
from lab.modules.stereo.sgm import (SGM_DIRECTIONS, quantize_costs, semi_global_matching, sgm_inputs,
                                    volume_range)
from lab.modules.stereo.steps import (DenseReconstruction, DisparityRange, FilteredDisparity, RectifiedPair,
                                      aggregate_costs, cost_volume, estimate_disparity_range,
                                      filter_disparity, left_right_check, reconstruct_points, rectify_pair,
                                      refine_subpixel, winner_take_all)
from lab.modules.stereo.winners import best_two_costs, costs_around, right_disparity

#: State names the viewer's interactions (:mod:`lab.viewer.interactions.stereo`) read by name.
VIEWS = ("left_raw", "calibration", "left", "right", "K", "baseline", "cost_volume", "aggregated_cost",
         "disparity_wta", "disparity_subpixel", "disparity", "depth", "cameras")

PIPELINE = Pipeline.build(
    name="stereo",
    title="Stereo disparity",
    summary="Dense depth from two views: rectify the pair, estimate the disparity range from matched "
            "features, compute a cost volume (SSD, NCC, census ...), "
            "aggregate it with semi-global matching, pick disparities, check them left against right, refine "
            "them below a pixel, filter holes and peaks, and triangulate a coloured point cloud with its "
            "uncertainty.",
    steps=[rectify_pair, estimate_disparity_range, cost_volume, aggregate_costs, winner_take_all,
           left_right_check, refine_subpixel, filter_disparity, reconstruct_points],
    datasets=[motorcycle, synthetic, folder],
    evaluations={"rectify_pair": evaluate_rectification, "winner_take_all": evaluate_winner_take_all,
                 "left_right_check": evaluate_left_right, "refine_subpixel": evaluate_subpixel,
                 "filter_disparity": evaluate_disparity, "reconstruct_points": evaluate_depth},
    views=VIEWS,
)

__all__ = [
    "BAD_THRESHOLDS", "COSTS", "HOLE", "MAX_VOLUME_ENTRIES", "MOTORCYCLE_BASELINE_M",
    "MOTORCYCLE_CENTRE_PX", "MOTORCYCLE_DOFFS_PX", "MOTORCYCLE_FOCAL_PX", "NCC_FLAT_VARIANCE",
    "PIPELINE", "SGM_DIRECTIONS", "VIEWS", "CensusRows", "Cost", "DenseReconstruction", "DisparityRange",
    "FilteredDisparity", "RangeMatches", "RectifiedPair", "RowWinners", "aggregate_costs",
    "best_two_costs", "best_two_costs_reference", "block_match_realtime",
    "block_match_realtime_reference", "block_matching_rows", "box_mean",
    "box_mean_reference", "census_costs", "census_rows", "census_transform",
    "census_transform_reference", "colorize_disparity", "cost_curves", "cost_volume", "costs_around",
    "depth_from_disparity", "disparity_errors", "error_map", "estimate_disparity_range",
    "estimate_max_disparity", "evaluate_depth", "evaluate_disparity", "evaluate_left_right",
    "evaluate_rectification", "evaluate_subpixel", "evaluate_winner_take_all", "fill_holes",
    "filter_disparity", "folder", "hamming_costs", "hamming_costs_reference", "lean_memory_bytes",
    "left_right_check", "match_range_features", "motorcycle", "quantize_costs", "rank_transform",
    "read_calibration", "read_disparity", "reconstruct_points", "rectify_pair", "refine_subpixel",
    "remove_peaks", "right_disparity", "right_disparity_reference", "row_misalignment",
    "semi_global_matching", "semi_global_matching_rows", "sgm_inputs", "sgm_reference", "shifted_right",
    "synthetic", "volume_curve", "volume_range", "winner_take_all",
]
