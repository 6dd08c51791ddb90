"""The building blocks of structure from motion, one small step each: the teaching pipeline of lesson 04.

The incremental reconstruction of :mod:`lab.modules.sfm` registers images one at a time inside one
generator step. This pipeline lays its building blocks out flat on a small scene made exactly (no
rendering, no matching), so each can be run, inspected and replaced by a student's function:

1. :func:`estimate_poses_linear` - linear PnP (DLT) of every camera from known 3D points
   (:func:`lab.geometry.pnp.pnp_dlt`; lesson task 1);
2. :func:`refine_poses` - non-linear PnP (:func:`lab.geometry.pnp.refine_pnp`);
3. :func:`triangulate_points_linear` - linear triangulation (DLT) of every point from all views that
   see it (:func:`lab.geometry.triangulation.triangulate_dlt`; lesson task 2);
4. :func:`refine_points_nonlinear` - non-linear triangulation
   (:func:`lab.geometry.triangulation.refine_points`);
5. :func:`jacobian_sparsity` - which entries of the bundle-adjustment Jacobian can be non-zero
   (:func:`lab.geometry.bundle_adjustment.bundle_sparsity`; lesson task 3);
6. :func:`bundle_adjust_scene` - bundle adjustment by ``scipy.optimize.least_squares`` with
   finite differences grouped by *that* pattern, so a wrong pattern shows in the final error.

It is not a registered module (the lesson names it ``lab.modules.sfm_basics:PIPELINE``). The steps
are in :mod:`lab.modules.sfm_basics.steps`, the dataset in :mod:`lab.modules.sfm_basics.datasets`,
the comparisons with the truth in :mod:`lab.modules.sfm_basics.evaluate`.

State names (float64 unless said):
    K              (3, 3)        the intrinsics of every camera (dataset)
    image_size     (2,) int      width, height in pixels (dataset)
    points3d       (N, 3)        known 3D points ("the map so far"), world frame (dataset)
    observations   Points2D      M pixels: ``view`` the camera, ``ids`` the 3D point (dataset)
    camera_indices (M,) int      = observations.view (dataset)
    point_indices  (M,) int      = observations.ids (dataset)
    num_cameras, num_points int  V and N (dataset)
    poses_linear   (V, 3, 4)     [R | t] of each camera from the linear PnP
    poses          (V, 3, 4)     refined by non-linear PnP;  cameras: Cameras (drawn)
    points_linear  (N, 3)        linear triangulation from ``poses``
    model          SparseModel   the scene: ``poses`` and the refined points, the observations as
                                 tracks (:func:`~lab.modules.sfm_basics.steps.scene_model`);
                                 cloud: PointCloud (drawn)
    sparsity       (2M, 6V + 3N) bool, the Jacobian's pattern
    adjusted_model SparseModel   after bundle adjustment; ba_cameras, ba_cloud, ba_cost (drawn)

Conventions (DESIGN.md section 3): OpenCV cameras, ``X_c = R X_w + t``, pixel (0, 0) the centre of
the top-left pixel. Reference: Hartley & Zisserman, Multiple View Geometry (2nd ed.), sections 7.1
(DLT for P), 12.2 (linear triangulation), A6.3 (sparse Levenberg-Marquardt); Triggs et al.,
"Bundle adjustment - a modern synthesis" (1999); the SciPy cookbook "Large-scale bundle adjustment
in scipy".
"""


from __future__ import annotations

from lab.core import Pipeline
from lab.modules.sfm_basics.datasets import synthetic
from lab.modules.sfm_basics.evaluate import (evaluate_bundle, evaluate_points, evaluate_points_linear,
                                             evaluate_poses, evaluate_poses_linear)
from lab.modules.sfm_basics.steps import (CAMERA_PARAMS, BundleAdjusted, RefinedPoints, RefinedPoses,
                                          bundle_adjust_scene, estimate_poses_linear, jacobian_sparsity,
                                          refine_points_nonlinear, refine_poses, scene_model,
                                          triangulate_points_linear)

PIPELINE = Pipeline.build(
    name="sfm_basics",
    title="Structure from motion: the building blocks",
    summary="Linear and non-linear PnP, linear and non-linear triangulation, and bundle adjustment with the "
            "Jacobian's sparsity pattern, each a step, on a small exact multi-view scene.",
    steps=[estimate_poses_linear, refine_poses, triangulate_points_linear, refine_points_nonlinear,
           jacobian_sparsity, bundle_adjust_scene],
    datasets=[synthetic],
    evaluations={"estimate_poses_linear": evaluate_poses_linear, "refine_poses": evaluate_poses,
                 "triangulate_points_linear": evaluate_points_linear,
                 "refine_points_nonlinear": evaluate_points, "bundle_adjust_scene": evaluate_bundle},
)

__all__ = [
    "CAMERA_PARAMS", "PIPELINE", "BundleAdjusted", "RefinedPoints", "RefinedPoses", "bundle_adjust_scene",
    "estimate_poses_linear", "jacobian_sparsity", "refine_points_nonlinear", "refine_poses", "scene_model",
    "synthetic", "triangulate_points_linear",
]
