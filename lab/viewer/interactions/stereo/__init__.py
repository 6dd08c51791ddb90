"""Interactions of the stereo module: what the generic drawing of a stereo session cannot show.

What the generic drawing shows already (:mod:`lab.viewer.renderers`): the photos and the rectified
pair (``left_raw``, ``right_raw``, ``left``, ``right``: Images), the final colour-mapped disparity
(``disparity_image``, after ``filter_disparity``), the point cloud (``points3d``) and both
rectified cameras as frustums (``cameras``, written by ``reconstruct_points`` with the right
camera ``baseline`` metres along x). The disparities of the earlier stages, the ground truth and
the errors are arrays, which it does not draw. So:

* **Disparity and error maps** (Images tab): the disparity of a chosen stage (winner-take-all,
  sub-pixel, final; by default the latest) colour-mapped on the scale of the true disparity, the
  true disparity itself, and the bad-pixel error map against it (green right, red wrong, blue a
  hole where the truth has a disparity) with its bad-pixel rate, when the session has a truth.
* **Matching costs of a pixel** (Plots tab): click a pixel of the left image, shown as a plane in
  the left camera's frustum in the 3D scene (viser scene images are clickable, GUI images are
  not), or type it: the cost over disparity of every matching cost (SSD, NSSD, SAD, ZSAD, NCC, rank,
  census) and of the session's aggregated volume, each normalised to [0, 1] so that they share an
  axis, each minimum marked, and the true disparity when known. The rectified rig (both cameras and
  the baseline) is drawn before ``reconstruct_points`` draws its cameras.
* **Baseline and depth resolution** (Plots tab): the depth uncertainty ``u_z = z^2 u_d / (f B)`` over
  depth for the current baseline and the previous ones; on the synthetic rig a slider restarts the
  session with another baseline and runs the pipeline to the point cloud again.

The math is in typed functions (tested directly), the classes only wire it to viser: the maps in
:mod:`.maps`, the cost curves in :mod:`.costs`, the baseline in :mod:`.baseline`; this package's
``__init__`` lists the interactions (``INTERACTIONS``) and re-exports their public names.
References: D. Scharstein and R. Szeliski, IJCV 47 (2002), sections 3 and 5.1 (costs, winner-take-all,
bad-pixel rates); R. Szeliski, *Computer Vision: Algorithms and Applications*, 2nd ed. (2022),
sections 12.1 (depth from disparity and its uncertainty) and 12.3 (matching costs).
"""

from __future__ import annotations

from lab.viewer.interactions import Interaction
from lab.viewer.interactions.stereo.baseline import (BASELINE_READS, RESTART_READS, BaselineExplorer,
                                                     BaselineRecord, chain_params, depth_range,
                                                     depth_uncertainty_curve, searchable_disparity,
                                                     uncertainty_plot)
from lab.viewer.interactions.stereo.costs import (COST_READS, CostCurveExplorer, CostCurves, MatchingSettings,
                                                  check_pick, click_to_left_pixel, cost_plot,
                                                  gather_cost_curves, last_params, matching_settings,
                                                  normalize_curves, rig_segments)
from lab.viewer.interactions.stereo.maps import (MAPS_READS, STAGES, DisparityMaps, StereoMaps,
                                                 disparity_stage, stereo_maps)

INTERACTIONS: list[type[Interaction]] = [DisparityMaps, CostCurveExplorer, BaselineExplorer]

__all__ = ["BASELINE_READS", "COST_READS", "INTERACTIONS", "MAPS_READS", "RESTART_READS", "STAGES",
           "BaselineExplorer", "BaselineRecord", "CostCurveExplorer", "CostCurves", "DisparityMaps",
           "MatchingSettings", "StereoMaps", "chain_params", "check_pick", "click_to_left_pixel", "cost_plot",
           "depth_range", "depth_uncertainty_curve", "disparity_stage", "gather_cost_curves", "last_params",
           "matching_settings", "normalize_curves", "rig_segments", "searchable_disparity", "stereo_maps",
           "uncertainty_plot"]
