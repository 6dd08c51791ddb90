"""The steps of Zhang's calibration, in pipeline order: each reads state by name and returns what it writes.

1. :func:`detect_corners`       photos -> the board's inner corners, sub-pixel
2. :func:`estimate_homographies` corners -> one board-to-image homography per view (normalized DLT)
3. :func:`estimate_intrinsics`  homographies -> ``K`` in closed form (the image of the absolute conic)
4. :func:`estimate_extrinsics`  homographies, ``K`` -> each view's pose
5. :func:`estimate_distortion`  corners, ``K``, poses -> radial ``k1, k2`` by linear least squares
6. :func:`refine_calibration`   everything at once by Levenberg-Marquardt on the reprojection error
7. :func:`undistort_image`      one photo with the lens distortion removed

The math of each step is in the file named after it; a step checks its inputs, calls that math and
packs the result.
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Annotated

import numpy as np

from lab.core import (Cameras, Curve, Image, ImageSet, InvalidControl, InvalidValue, Mesh, Points2D, Progress,
                      Range, Segments2D, StepFailed, Warnings, metric, step_result)
from lab.geometry.camera import as_distortion, as_intrinsics, optimal_new_camera_matrix, undistortion_map
from lab.modules.calibration.board import Checkerboard
from lab.modules.calibration.corners import find_boards, refine_corners
from lab.modules.calibration.distortion import linear_radial_distortion
from lab.modules.calibration.drawing import (board_mesh, camera_rig, cost_curve, per_view_curve,
                                             residual_segments, view_names)
from lab.modules.calibration.extrinsics import poses_from_homographies
from lab.modules.calibration.homography import dlt_homographies, stack_views
from lab.modules.calibration.intrinsics import absolute_conic, conic_constraints, intrinsics_from_conic
from lab.modules.calibration.observations import Observations, check_corners, check_stack
from lab.modules.calibration.refinement import (Fit, ReprojectionProblem, free_parameters,
                                                levenberg_marquardt, standard_deviations)


# ----------------------------------------------------------------------------------------------------
# 1. Corner detection
# ----------------------------------------------------------------------------------------------------
@step_result
class CornerDetection:
    """Result of :func:`detect_corners`."""

    corners: Points2D
    board_points: np.ndarray
    views: np.ndarray
    warnings: Warnings
    views_found: int = metric("photos in which the whole board was found")
    views_total: int = metric("photos")


def detect_corners(images: ImageSet, board: Checkerboard, *, subpixel: bool = True,
                   window: Annotated[int, Range(2, 15)] = 5) -> CornerDetection:
    """Find the board's inner corners in every photo, then refine them to sub-pixel accuracy.

    The coarse detection is OpenCV's (``cv2.findChessboardCorners`` with adaptive thresholding,
    on the 8-bit grayscale photo): it finds the quads of the pattern and orders the corners row
    by row. Corner 0 is then put at the black square's end (:func:`~lab.modules.calibration.corners.orient`),
    so ids match ``board.object_points()`` in every view. The sub-pixel refinement is written here
    (:func:`refine_corners`, what ``cv2.cornerSubPix`` computes), vectorized over all corners
    of all photos.

    Args:
        subpixel: refine the corners to sub-pixel accuracy (Förstner's iteration).
        window: half the side of the refinement window in pixels (OpenCV's winSize); keep it
            below half a square.

    Returns ``corners`` (Points2D: ``view`` = image index, ``ids`` = board corner index,
    ``image`` = "images"), ``board_points`` ``(N, 3)``, ``views`` ``(M,)`` (images where the whole
    board was found, ascending) and a warning naming each photo without a board.

    Reference: Z. Zhang (2000), section 4 (the corners as the input of calibration); Förstner and
    Gülch (1987) for the refinement.
    """
    if not isinstance(images, ImageSet) or len(images) == 0:
        raise InvalidValue("images", "needs at least one photo")
    if not isinstance(board, Checkerboard):
        raise InvalidValue("board", f"expected a Checkerboard, got {type(board).__name__}")
    found = find_boards(images, board)
    if not found.views:
        raise StepFailed("images", f"no board of {board.columns}x{board.rows} inner corners was found in any "
                                   f"of the {len(images)} photos; check columns and rows (inner corners, not "
                                   "squares)")
    _check_same_size(images, found.views)
    n = board.num_corners
    xy = np.concatenate(found.xy)
    if subpixel:
        stack = np.repeat(np.arange(len(found.views)), n)  # each corner's photo in found.grays
        xy = refine_corners(np.stack(found.grays), xy, stack, window=window)
    views = np.array(found.views, dtype=np.int64)
    corners = Points2D(xy, view=np.repeat(views, n), ids=np.tile(np.arange(n), len(views)), image="images")
    return CornerDetection(corners, board.object_points(), views, tuple(found.warnings), len(views),
                           len(images))


def _check_same_size(images: ImageSet, views: list[int]) -> None:
    if len({(images[i].width, images[i].height) for i in views}) > 1:
        listing = ", ".join(f"{images.names[i]} {images[i].width}x{images[i].height}" for i in views)
        raise InvalidValue("images", "the photos of one calibration must all have the same size; boards "
                                     f"were found in photos of different sizes: {listing}")


# ----------------------------------------------------------------------------------------------------
# 2. Homographies
# ----------------------------------------------------------------------------------------------------
def estimate_homographies(corners: Points2D, board_points: np.ndarray, *,
                          normalize: bool = True) -> Annotated[np.ndarray, "homographies"]:
    """One homography per view, board plane ``(X, Y, 1)`` -> pixels, by the (normalized) DLT.

    Each correspondence ``(X, Y) -> (u, v)`` gives two rows of ``A h = 0``::

        [X, Y, 1, 0, 0, 0, -u X, -u Y, -u]
        [0, 0, 0, X, Y, 1, -v X, -v Y, -v]

    and ``h`` is the right singular vector of ``A`` with the smallest singular value. With
    ``normalize`` both point sets are first moved to their centroid and scaled to mean distance
    sqrt(2) (``T_img``, ``T_board``), and ``H = T_img^-1 H_n T_board``. Without it, pixels
    (hundreds) and metres (hundredths) make ``A`` badly conditioned, and the algebraic error it
    minimizes depends on the arbitrary origin and scale of the coordinates: move the image origin
    and the unnormalized answer changes, the normalized one does not (H&Z section 4.4.2).
    All views are solved at once by one batched SVD (views with fewer points are padded with zero
    rows, which change nothing). ``cv2.findHomography(board_xy, pixels, 0)`` starts from a
    normalized DLT too but then refines H by Levenberg-Marquardt on the reprojection error (on noisy
    corners about 1 % away from the DLT's answer).

    Args:
        normalize: apply Hartley's normalization (H&Z algorithm 4.2) before the DLT.

    A view may hold any subset of the board's corners, in any order (each is paired with its board
    point by ``corners.ids``).

    Returns ``(M, 3, 3)`` with ``H[2, 2] = 1``, in the order of the sorted unique ``corners.view``.

    Reference: Hartley & Zisserman, Multiple View Geometry (2nd ed.), section 4.1 (DLT) and 4.4
    (normalization, algorithm 4.2); Zhang (2000), appendix A.
    """
    corners, board_points = check_corners(corners, board_points)
    return dlt_homographies(stack_views(corners, board_points), normalize=normalize)


# ----------------------------------------------------------------------------------------------------
# 3. Intrinsics (closed form)
# ----------------------------------------------------------------------------------------------------
def estimate_intrinsics(homographies: np.ndarray, *,
                        zero_skew: bool = False) -> Annotated[np.ndarray, "K_init"]:
    """Closed-form intrinsics from the image of the absolute conic, ``B = K^-T K^-1`` (up to scale).

    The columns ``h1, h2`` of each homography are the images of two orthonormal directions, so
    ``h1^T B h2 = 0`` and ``h1^T B h1 = h2^T B h2``: with ``h_i^T B h_j = v_ij^T b`` these are two
    rows ``[v12; v11 - v22]`` of ``V b = 0``, ``b`` the right singular vector of ``V`` with the
    smallest singular value. ``zero_skew`` adds the row ``[0, 1, 0, 0, 0, 0]`` (``B12 = 0``,
    heavily weighted). ``K`` then follows in closed form (Zhang, appendix B)::

        v0 = (B12 B13 - B11 B23) / (B11 B22 - B12^2)
        lambda = B33 - (B13^2 + v0 (B12 B13 - B11 B23)) / B11
        alpha = sqrt(lambda / B11),  beta = sqrt(lambda B11 / (B11 B22 - B12^2))
        gamma = -B12 alpha^2 beta / lambda,  u0 = gamma v0 / beta - B13 alpha^2 / lambda

    Each homography is scaled to unit norm first, so every view weighs the same.

    Args:
        zero_skew: assume the pixel axes are perpendicular (skew 0); then 2 views suffice.

    Returns ``K`` ``(3, 3)`` = ``[[alpha, gamma, u0], [0, beta, v0], [0, 0, 1]]``. OpenCV's
    ``cv2.calibrateCamera`` starts from a different guess (``initIntrinsicParams2D``, principal
    point at the image centre); this is Zhang's.

    Reference: Z. Zhang, "A flexible new technique for camera calibration" (2000), section 3.1
    and appendix B; Hartley & Zisserman (2nd ed.), section 8.8.
    """
    H = check_stack(homographies, "homographies", (3, 3))
    needed = 2 if zero_skew else 3
    if len(H) < needed:
        which = " (zero_skew)" if zero_skew else " (or 2 with zero_skew)"
        raise InvalidValue("homographies", f"Zhang's closed form needs at least {needed} views{which}, "
                                           f"got {len(H)}")
    b = absolute_conic(conic_constraints(H, zero_skew=zero_skew))
    return intrinsics_from_conic(b, zero_skew=zero_skew)


# ----------------------------------------------------------------------------------------------------
# 4. Extrinsics (closed form)
# ----------------------------------------------------------------------------------------------------
@step_result
class Extrinsics:
    """Result of :func:`estimate_extrinsics`: board-to-camera poses, one per view."""

    R_init: np.ndarray
    t_init: np.ndarray


def estimate_extrinsics(homographies: np.ndarray, K_init: np.ndarray) -> Extrinsics:
    """Each view's pose from its homography and ``K``: ``[r1 r2 t] = lambda K^-1 H``.

    ``lambda = 1 / |K^-1 h1|`` (here the mean of ``|K^-1 h1|`` and ``|K^-1 h2|``, which are equal
    without noise), signed so the board lies in front of the camera (``t_z > 0``);
    ``r3 = r1 x r2``. With noise ``[r1 r2 r3]`` is not a rotation: it is replaced by the nearest
    rotation in Frobenius norm, ``U V^T`` of its SVD, with the sign fixed so that det = +1.

    Returns ``R_init`` ``(M, 3, 3)`` and ``t_init`` ``(M, 3)`` (``X_c = R X_board + t``).
    Corresponds to the pose part of ``cv2.calibrateCamera``'s initialization (``cv2.solvePnP``
    on a plane does the same from a homography).

    Reference: Z. Zhang (2000), section 3.1 (eq. 13) and appendix C.
    """
    H = check_stack(homographies, "homographies", (3, 3))
    R, t = poses_from_homographies(H, as_intrinsics(K_init))
    return Extrinsics(R, t)


# ----------------------------------------------------------------------------------------------------
# 5. Radial distortion (linear)
# ----------------------------------------------------------------------------------------------------
def estimate_distortion(corners: Points2D, board_points: np.ndarray, K_init: np.ndarray, R_init: np.ndarray,
                        t_init: np.ndarray) -> Annotated[np.ndarray, "dist_init"]:
    """Radial distortion ``k1, k2`` by linear least squares, the intrinsics and poses held fixed.

    With ``(u, v)`` the ideal (undistorted) projection of a board corner, ``(x, y)`` its ideal
    normalized coordinates and ``r^2 = x^2 + y^2``, the observed ``(u_d, v_d)`` satisfy::

        u_d - u = (u - u0) (k1 r^2 + k2 r^4)
        v_d - v = (v - v0) (k1 r^2 + k2 r^4)

    two linear equations per corner in ``(k1, k2)``, stacked over all corners and solved by least
    squares (``D k = d``). The tangential terms and ``k3`` start at 0.

    Returns ``(5,)``: ``(k1, k2, 0, 0, 0)`` in OpenCV's order.

    Reference: Z. Zhang (2000), section 3.3, eq. (13).
    """
    corners, board_points = check_corners(corners, board_points)
    K = as_intrinsics(K_init)
    R = check_stack(R_init, "R_init", (3, 3))
    t = check_stack(t_init, "t_init", (3,), len(R))
    return linear_radial_distortion(Observations.of(corners, board_points, len(R)), K, R, t)


# ----------------------------------------------------------------------------------------------------
# 6. Joint refinement (Levenberg-Marquardt)
# ----------------------------------------------------------------------------------------------------
@step_result
class Calibration:
    """Result of :func:`refine_calibration`."""

    K: np.ndarray
    dist: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    cameras: Cameras
    board_mesh: Mesh
    reprojected: Points2D
    residuals: Segments2D
    per_view_rms: Curve
    std_intrinsics: np.ndarray
    cost: Curve
    rms_px: float = metric("root mean square reprojection error over all corners", unit="px")
    fx: float = metric("focal length along x", unit="px")
    fy: float = metric("focal length along y", unit="px")
    cx: float = metric("principal point x", unit="px")
    cy: float = metric("principal point y", unit="px")
    skew: float = metric("skew", unit="px")
    k1: float = metric("radial distortion k1")
    k2: float = metric("radial distortion k2")
    p1: float = metric("tangential distortion p1")
    p2: float = metric("tangential distortion p2")
    k3: float = metric("radial distortion k3")
    fx_std: float = metric("standard deviation of fx (Bouguet prints 3 times this)", unit="px")
    fy_std: float = metric("standard deviation of fy", unit="px")
    cx_std: float = metric("standard deviation of cx", unit="px")
    cy_std: float = metric("standard deviation of cy", unit="px")
    skew_std: float = metric("standard deviation of the skew (0 when fixed)", unit="px")
    k1_std: float = metric("standard deviation of k1")
    k2_std: float = metric("standard deviation of k2")
    p1_std: float = metric("standard deviation of p1 (0 when fixed)")
    p2_std: float = metric("standard deviation of p2 (0 when fixed)")
    k3_std: float = metric("standard deviation of k3 (0 when fixed)")
    per_view_rms_px: list[float] = metric("RMS reprojection error of each used view", unit="px")
    worst_view: int = metric("image index of the view with the largest RMS")
    iterations: int = metric("Levenberg-Marquardt iterations")


def refine_calibration(corners: Points2D, board_points: np.ndarray, K_init: np.ndarray, dist_init: np.ndarray,
                       R_init: np.ndarray, t_init: np.ndarray, images: ImageSet | None = None,
                       board: Checkerboard | None = None, *, estimate_skew: bool = False,
                       fix_k3: bool = False, fix_tangential: bool = False,
                       max_iterations: Annotated[int, Range(1, 500)] = 100,
                       residual_scale: Annotated[float, Range(1.0, 1000.0)] = 100.0,
                       ) -> Generator[Progress, None, Calibration]:
    """Minimize the reprojection error over all parameters at once by Levenberg-Marquardt.

    Cost: ``sum_v sum_j |project(K, dist, R_v X_j + t_v) - x_vj|^2`` over fx, fy, cx, cy (skew
    when ``estimate_skew``), the 5 distortion terms (``k3`` and ``p1, p2`` can be held at 0) and
    every view's pose as axis-angle ``w_v`` plus ``t_v``. The Jacobian is analytic: pinhole and
    distortion derivatives chained with ``dX_c/dw = -[R X]_x J_left(w)``. Its structure (each
    pose touches only its own view's corners) makes ``J^T J`` an arrow matrix; each damped step
    ``(J^T J + lambda diag(J^T J)) delta = -J^T r`` (Marquardt's scaling) is solved by the Schur
    complement on the 6x6 pose blocks, as in bundle adjustment. ``lambda`` shrinks 10x after a
    step that lowers the cost and grows 10x after one that does not. Yields the RMS error every
    iteration (with the reprojected corners as a preview); stops when the relative decrease of the
    cost or the step falls below 1e-10.

    Standard deviations: ``sigma^2 = RSS / (m - n)`` (m residuals, n free parameters) times the
    diagonal of ``(J^T J)^-1`` at the solution, whose intrinsic block is the inverse of the Schur
    complement; ``cv2.calibrateCameraExtended`` reports the same ``stdDeviationsIntrinsics`` and
    Bouguet's toolbox prints three times them as the error bars.

    Args:
        estimate_skew: optimize the skew too (else it is held at 0, as OpenCV does).
        fix_k3: hold k3 at 0 (OpenCV's CALIB_FIX_K3).
        fix_tangential: hold p1 and p2 at 0 (OpenCV's CALIB_ZERO_TANGENT_DIST).
        max_iterations: most Levenberg-Marquardt iterations.
        residual_scale: magnification of the residual segments drawn on the photos.

    Corresponds to ``cv2.calibrateCamera`` (its own Levenberg-Marquardt, ``CvLevMarq``), started
    from Zhang's closed form instead of OpenCV's ``initIntrinsicParams2D``.

    Reference: Z. Zhang (2000), sections 3.2 and 3.3 (maximum-likelihood estimation, complete
    maximum-likelihood estimation); K. Levenberg (1944), D. Marquardt (1963); Triggs et al.,
    "Bundle adjustment - a modern synthesis" (2000), section 6.1 (the Schur complement);
    J.-Y. Bouguet, Camera Calibration Toolbox for Matlab (uncertainties).
    """
    corners, board_points = check_corners(corners, board_points)
    K0, dist0 = as_intrinsics(K_init), as_distortion(dist_init)
    R0 = check_stack(R_init, "R_init", (3, 3))
    t0 = check_stack(t_init, "t_init", (3,), len(R0))
    seen = Observations.of(corners, board_points, len(R0))
    free = free_parameters(estimate_skew=estimate_skew, fix_k3=fix_k3, fix_tangential=fix_tangential)
    problem = ReprojectionProblem(seen, free)
    fit = yield from levenberg_marquardt(problem, K0, dist0, R0, t0, max_iterations=max_iterations)
    return _calibration(problem, fit, images, board, board_points, residual_scale)


def _calibration(problem: ReprojectionProblem, fit: Fit, images: ImageSet | None, board: Checkerboard | None,
                 board_points: np.ndarray, residual_scale: float) -> Calibration:
    """The step's result from where Levenberg-Marquardt stopped: parameters, drawn values, metrics."""
    seen, theta, K, dist, rotations = problem.seen, fit.theta, fit.K, fit.dist, fit.rotations
    std = standard_deviations(problem, fit)
    per_view = problem.per_view_rms(fit.r)
    r = problem.by_observation(fit.r)
    return Calibration(
        K=K, dist=dist, rotations=rotations, translations=fit.t,
        cameras=camera_rig(K, dist, rotations, fit.t, seen.views, per_view, images),
        board_mesh=board_mesh(board, board_points),
        reprojected=Points2D(seen.pixels + r, view=seen.image, ids=seen.ids, image="images"),
        residuals=residual_segments(seen, r, residual_scale),
        per_view_rms=per_view_curve(per_view, view_names(images, seen.views)), std_intrinsics=std,
        cost=cost_curve(fit.history), rms_px=float(np.sqrt(fit.cost / len(seen))),
        fx=theta[0], fy=theta[1], cx=theta[2], cy=theta[3], skew=theta[4], k1=theta[5], k2=theta[6],
        p1=theta[7], p2=theta[8], k3=theta[9], fx_std=std[0], fy_std=std[1], cx_std=std[2], cy_std=std[3],
        skew_std=std[4], k1_std=std[5], k2_std=std[6], p1_std=std[7], p2_std=std[8], k3_std=std[9],
        per_view_rms_px=[float(v) for v in per_view], worst_view=int(seen.views[int(np.argmax(per_view))]),
        iterations=fit.iterations)


# ----------------------------------------------------------------------------------------------------
# 7. Undistortion
# ----------------------------------------------------------------------------------------------------
def undistort_image(images: ImageSet, K: np.ndarray, dist: np.ndarray, *,
                    view: Annotated[int, Range(0, None)] = 0,
                    alpha: Annotated[float, Range(0.0, 1.0)] = 0.0) -> Annotated[Image, "undistorted"]:
    """One photo with the lens distortion removed.

    The new camera matrix follows ``alpha`` as ``cv2.getOptimalNewCameraMatrix``: 0 keeps only
    valid pixels (the largest rectangle inside the undistorted image), 1 keeps every source
    pixel (black corners), in between interpolates (:func:`lab.geometry.camera.optimal_new_camera_matrix`).
    For every output pixel ``p``, ``K_new^-1 p`` is distorted and mapped by ``K`` to the source
    pixel to sample (:func:`lab.geometry.camera.undistortion_map`, what
    ``cv2.initUndistortRectifyMap`` computes); the photo is then sampled bilinearly with
    ``cv2.remap`` (black outside).

    Args:
        view: index of the photo to undistort.
        alpha: 0 = crop to valid pixels, 1 = keep all source pixels.

    Reference: Hartley & Zisserman (2nd ed.), section 7.4 (radial distortion); the OpenCV
    documentation of ``initUndistortRectifyMap`` and ``getOptimalNewCameraMatrix``.
    """
    import cv2

    if not isinstance(images, ImageSet) or len(images) == 0:
        raise InvalidValue("images", "needs at least one photo")
    if not 0 <= view < len(images):
        raise InvalidControl("view", f"must be an image index from 0 to {len(images) - 1}, got {view}")
    K = as_intrinsics(K)
    dist = as_distortion(dist)
    image = images[view]
    size = (image.width, image.height)
    K_new = optimal_new_camera_matrix(K, dist, size, alpha=alpha)
    mapping = undistortion_map(K, dist, size, K_new=K_new).astype(np.float32)
    pixels = cv2.remap(image.pixels, mapping[..., 0], mapping[..., 1], interpolation=cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return Image(np.clip(pixels, 0.0, 1.0), name=f"{image.name or f'view {view}'} (undistorted)")


__all__ = ["Calibration", "CornerDetection", "Extrinsics", "detect_corners", "estimate_distortion",
           "estimate_extrinsics", "estimate_homographies", "estimate_intrinsics", "refine_calibration",
           "undistort_image"]
