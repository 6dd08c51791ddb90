"""Camera calibration with Zhang's method, step by step.

Reference: Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000
(sections and appendices named in each step); J.-Y. Bouguet's Camera Calibration Toolbox for
Matlab (parameter uncertainties, +-3 sigma); Hartley & Zisserman, Multiple View Geometry, 2nd ed.,
section 4.4 (normalized DLT).

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
    ...
"""
# STUB: being implemented (contract only). See the helper's task.
