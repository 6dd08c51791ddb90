"""Camera calibration with Zhang's method, step by step.

Reference: Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000
(sections and appendices named in each step); J.-Y. Bouguet's Camera Calibration Toolbox for
Matlab (parameter uncertainties, +-3 sigma); Hartley & Zisserman, Multiple View Geometry, 2nd ed.,
section 4.4 (normalized DLT).

The package (this file is its only import surface):

    steps.py         the seven steps in pipeline order, each with its result class
    corners.py       board detection (OpenCV) and Förstner's sub-pixel refinement
    homography.py    the normalized DLT, all views in one batched SVD
    intrinsics.py    Zhang's closed form: the image of the absolute conic -> K
    extrinsics.py    each view's pose from its homography and K
    distortion.py    radial k1, k2 by linear least squares
    refinement.py    Levenberg-Marquardt on the reprojection error (Schur complement), uncertainties
    observations.py  input checks; the corners sorted by view
    drawing.py       the cameras, board, residuals and curves the viewer draws
    evaluate.py      comparisons with the synthetic truth, run after each step
    export.py        the OpenCV YAML calibration file
    board.py         the Checkerboard target
    datasets.py      the synthetic board with exact truth (rendering.py draws it) and a folder of photos

State names (all float64 unless said):
    images        ImageSet          the photos (dataset)
    board         Checkerboard      inner-corner grid size and square size (dataset)
    corners       Points2D          detected corners; ``view`` = image index, ``ids`` = board corner index
    board_points  (N, 3)            board corner coordinates in the board frame (Z = 0), metres
    views         (M,) int          indices of the images where a board was found, ascending
    homographies  (M, 3, 3)         board (X, Y, 1) -> pixels, one per used view, H[2, 2] = 1
    K_init        (3, 3)            closed-form intrinsics
    R_init        (M, 3, 3)         closed-form rotations (board -> camera)
    t_init        (M, 3)            closed-form translations
    dist_init     (5,)              linear radial distortion (k1, k2, 0, 0, 0)
    K, dist, rotations, translations   refined by Levenberg-Marquardt
    cameras       Cameras           the M cameras around the board (board frame = world), coloured by RMS
    board_mesh    Mesh              the board's squares in the board frame
    reprojected   Points2D          board corners projected with the refined parameters
    residuals     Segments2D        detected corner -> detected + scale * (reprojected - detected)
    per_view_rms  Curve             RMS reprojection error per view (bars named by photo)
    std_intrinsics (10,)            standard deviations of fx fy cx cy skew k1 k2 p1 p2 k3
    cost          Curve             RMS reprojection error per Levenberg-Marquardt iteration
    undistorted   Image             one photo with the lens distortion removed

Views are always ordered by image index: the ``m``-th homography, rotation and translation belong
to image ``views[m]`` (the ``m``-th of the sorted unique ``corners.view``).
"""

from __future__ import annotations

from lab.core import Pipeline
from lab.modules.calibration.board import BACKGROUND, BLACK, WHITE, Checkerboard
from lab.modules.calibration.corners import refine_corners
from lab.modules.calibration.datasets import folder, synthetic
from lab.modules.calibration.evaluate import (EVALUATIONS, evaluate_distortion, evaluate_extrinsics,
                                              evaluate_homographies, evaluate_intrinsics, evaluate_refinement)
from lab.modules.calibration.export import OPENCV_YAML, write_opencv_yaml
from lab.modules.calibration.refinement import INTRINSIC_NAMES
from lab.modules.calibration.steps import (Calibration, CornerDetection, Extrinsics, detect_corners,
                                           estimate_distortion, estimate_extrinsics, estimate_homographies,
                                           estimate_intrinsics, refine_calibration, undistort_image)

PIPELINE = Pipeline.build(
    name="calibration",
    title="Camera calibration",
    summary="Zhang's method step by step: detect the corners of a checkerboard, fit a homography per view, "
            "solve for the intrinsics and poses in closed form, estimate radial distortion, refine "
            "everything by Levenberg-Marquardt, and undistort a photo.",
    steps=[detect_corners, estimate_homographies, estimate_intrinsics, estimate_extrinsics,
           estimate_distortion, refine_calibration, undistort_image],
    datasets=[synthetic, folder],
    evaluations=EVALUATIONS,
    exports=[OPENCV_YAML],
    # The viewer draws corners, residuals and cameras on the photos they name (image="images").
    views=["images"],
)

__all__ = [
    "BACKGROUND", "BLACK", "INTRINSIC_NAMES", "OPENCV_YAML", "PIPELINE", "WHITE", "Calibration",
    "Checkerboard", "CornerDetection", "Extrinsics", "detect_corners", "estimate_distortion",
    "estimate_extrinsics", "estimate_homographies", "estimate_intrinsics", "evaluate_distortion",
    "evaluate_extrinsics", "evaluate_homographies", "evaluate_intrinsics", "evaluate_refinement", "folder",
    "refine_calibration", "refine_corners", "synthetic", "undistort_image", "write_opencv_yaml",
]
