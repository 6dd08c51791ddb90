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

from typing import Annotated, Any, Generator

import numpy as np

from lab.core.step import step_result, Warnings
from lab.core import (Cameras, Curve, Image, ImageSet, InvalidControl, InvalidValue, Mesh, Pipeline, Points2D, Progress,
                      Range, Segments2D, StepFailed, metric)
from lab.data.checkerboard import Checkerboard, folder, synthetic
from lab.geometry.camera import (as_distortion, as_intrinsics, distort_components,
                                 optimal_new_camera_matrix, undistortion_map)
from lab.geometry.homogeneous import apply_homography, hartley_normalization
from lab.geometry.rotations import (matrix_to_rotvec, nearest_rotation, rotation_angle_deg, rotvec_to_matrix,
                                    so3_left_jacobian)

#: Names of the intrinsic parameters, in the order of ``std_intrinsics``.
INTRINSIC_NAMES: tuple[str, ...] = ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3")


# ----------------------------------------------------------------------------------------------------
# Input checks shared by the steps
# ----------------------------------------------------------------------------------------------------
def _check_corners(corners: Any, board_points: Any) -> tuple[Points2D, np.ndarray]:
    if not isinstance(corners, Points2D):
        raise InvalidValue("corners", f"expected Points2D, got {type(corners).__name__}")
    if corners.ids is None:
        raise InvalidValue("corners", "needs ids (the board corner each point observes)")
    board_points = np.asarray(board_points, dtype=np.float64)
    if board_points.ndim != 2 or board_points.shape[1] != 3 or len(board_points) < 4:
        raise InvalidValue("board_points", f"expected shape (N >= 4, 3), got {board_points.shape}")
    if not np.all(np.isfinite(board_points)):
        raise InvalidValue("board_points", "contains NaN or infinite entries")
    if len(corners) and (corners.ids.min() < 0 or corners.ids.max() >= len(board_points)):
        raise InvalidValue("corners", f"ids must index board_points (0 .. {len(board_points) - 1})")
    if len(corners) == 0:
        raise InvalidValue("corners", "no corners")
    return corners, board_points


def _views_of(corners: Points2D) -> tuple[np.ndarray, np.ndarray]:
    """Sorted image indices of the views and, per corner, its position in that list."""
    view = corners.view if corners.view is not None else np.zeros(len(corners), dtype=np.int64)
    views, position = np.unique(view, return_inverse=True)
    return views, position.ravel()


def _check_stack(value: Any, name: str, shape: tuple[int, ...], count: int | None = None) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != len(shape) + 1 or array.shape[1:] != shape or (count is not None and len(array) != count):
        want = f"({count if count is not None else 'M'}, {', '.join(map(str, shape))})"
        raise InvalidValue(name, f"expected shape {want}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return array


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


def refine_corners(gray: np.ndarray, xy: np.ndarray, view: np.ndarray | None = None, *, window: int = 5,
                   max_iterations: int = 30, epsilon: float = 1e-3) -> np.ndarray:
    """Sub-pixel corner positions by Förstner's gradient-orthogonality iteration, all corners at once.

    At the true corner ``q`` every image gradient ``g_p`` near it is orthogonal to ``p - q`` (on an
    edge ``g_p`` is normal to the edge through ``q``; in a flat region ``g_p = 0``). Minimizing
    ``sum_p w_p (g_p^T (p - q))^2`` over the window gives the 2x2 linear system
    ``(sum w g g^T) q = sum w g g^T p``; iterate with the window re-centred on the new ``q``.
    This is exactly ``cv2.cornerSubPix(gray, xy, (window, window), (-1, -1), criteria)``: the
    window is ``2 window + 1`` pixels wide, sampled bilinearly around ``q`` (``cv2.getRectSubPix``,
    border replicated), gradients are central differences, weights ``exp(-(dx^2 + dy^2) / window^2)``;
    a corner stops when it moves less than ``epsilon`` px or leaves the image, and one that ends
    up more than ``window`` px from its start keeps its start.

    Args:
        gray: ``(H, W)`` or a stack ``(V, H, W)`` of grayscale images (float).
        xy: ``(N, 2)`` initial corners in pixels.
        view: ``(N,)`` index into the stack for each corner (None: all on image 0).
        window: half the side of the search window, in pixels.
        max_iterations: most iterations per corner.
        epsilon: stop when a corner moves less than this (pixels).

    Returns:
        ``(N, 2)`` refined corners.

    Reference: W. Förstner and E. Gülch, "A fast operator for detection and precise location of
    distinct points, corners and centres of circular features", ISPRS 1987; OpenCV's
    ``cornerSubPix`` (imgproc/src/cornersubpix.cpp).
    """
    stack = np.asarray(gray, dtype=np.float32)
    if stack.ndim == 2:
        stack = stack[None]
    if stack.ndim != 3:
        raise InvalidValue("gray", f"expected (H, W) or (V, H, W), got shape {stack.shape}")
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    count, height, width = stack.shape
    view = np.zeros(len(xy), dtype=np.intp) if view is None else np.asarray(view, dtype=np.intp)
    if len(view) != len(xy) or (len(view) and (view.min() < 0 or view.max() >= count)):
        raise InvalidValue("view", "needs one image index per corner")
    if int(window) < 1:
        raise InvalidControl("window", f"must be at least 1, got {window}")
    half = int(window)
    size = 2 * half + 1
    grid = ((np.arange(size) - half) / half) ** 2
    weights = np.exp(-grid[:, None] - grid[None, :]).astype(np.float32)  # (S, S), S = 2 half + 1
    px = (np.arange(size, dtype=np.float32) - half)[None, :]  # x offset of window column j
    py = (np.arange(size, dtype=np.float32) - half)[:, None]  # y offset of window row i
    window_weights = np.stack([weights, weights * px, weights * py], axis=-1).reshape(-1, 3)  # (S^2, 3)
    reach = np.arange(-half - 1, half + 3)  # pixels under the bilinear (S + 2)^2 patch and its 1 px border
    flat = stack.reshape(-1)
    start = xy.copy()
    q = xy.copy()
    active = np.arange(len(q))
    eps2 = float(epsilon) ** 2
    for _ in range(int(max_iterations)):
        if len(active) == 0:
            break
        centre = q[active]
        # one gather of the (S + 3)^2 pixels around each centre (border replicated), then a
        # bilinear patch in which all pixels share the centre's fractional weights (cv2.getRectSubPix)
        base = np.floor(centre).astype(np.intp)
        frac = (centre - base).astype(np.float32)
        cols = np.clip(base[:, 0, None] + reach, 0, width - 1)
        rows = np.clip(base[:, 1, None] + reach, 0, height - 1)
        pixels = flat[(view[active] * (height * width))[:, None, None] + rows[:, :, None] * width + cols[:, None, :]]
        fx = frac[:, 0, None, None]
        fy = frac[:, 1, None, None]
        top = pixels[:, :-1, :-1] + fx * (pixels[:, :-1, 1:] - pixels[:, :-1, :-1])
        bottom = pixels[:, 1:, :-1] + fx * (pixels[:, 1:, 1:] - pixels[:, 1:, :-1])
        patch = top + fy * (bottom - top)  # (n, S + 2, S + 2)
        gx = patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2]
        gy = patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1]
        products = np.stack([gx * gx, gx * gy, gy * gy], axis=1).reshape(len(active), 3, -1)
        sums = (products @ window_weights).astype(np.float64)  # (n, 3, 3): sum of g g^T times w, w px, w py
        a, b, c = sums[:, 0, 0], sums[:, 1, 0], sums[:, 2, 0]
        bb1 = sums[:, 0, 1] + sums[:, 1, 2]  # sum w (gxx px + gxy py)
        bb2 = sums[:, 1, 1] + sums[:, 2, 2]  # sum w (gxy px + gyy py)
        det = a * c - b * b
        solvable = np.abs(det) > np.finfo(np.float64).eps ** 2
        safe = np.where(solvable, det, 1.0)
        step = np.stack([(c * bb1 - b * bb2) / safe, (a * bb2 - b * bb1) / safe], axis=1)
        moved = np.where(solvable[:, None], centre + step, centre)
        q[active] = moved
        inside = (moved[:, 0] >= 0) & (moved[:, 0] < width) & (moved[:, 1] >= 0) & (moved[:, 1] < height)
        active = active[solvable & inside & (np.sum(step * step, axis=1) > eps2)]
    far = np.any(np.abs(q - start) > half, axis=1)
    q[far] = start[far]
    return q


def _orient(gray: np.ndarray, xy: np.ndarray, board: Checkerboard) -> np.ndarray:
    """Put corner 0 where the square between corners 0, 1, columns, columns + 1 is black.

    ``cv2.findChessboardCorners`` may start from either end of the board. When ``columns + rows``
    is odd the board has no 180-degree symmetry, and the colour of that square tells the ends
    apart (reverse the order if it is lighter than its neighbour along the row).
    """
    if (board.columns + board.rows) % 2 == 0:
        return xy
    grid = xy.reshape(board.rows, board.columns, 2)
    first = grid[:2, :2].reshape(-1, 2).mean(axis=0)
    neighbour = grid[:2, 1:3].reshape(-1, 2).mean(axis=0)
    h, w = gray.shape
    offsets = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1]), -1).reshape(1, 9, 2)
    probe = np.stack([first, neighbour])[:, None, :] + offsets
    cols = np.clip(np.round(probe[..., 0]).astype(int), 0, w - 1)
    rows = np.clip(np.round(probe[..., 1]).astype(int), 0, h - 1)
    shade = gray[rows, cols].mean(axis=1)
    return xy[::-1].copy() if shade[0] > shade[1] else xy


def detect_corners(images: ImageSet, board: Checkerboard, *, subpixel: bool = True,
                   window: Annotated[int, Range(2, 15)] = 5) -> CornerDetection:
    """Find the board's inner corners in every photo, then refine them to sub-pixel accuracy.

    The coarse detection is OpenCV's (``cv2.findChessboardCorners`` with adaptive thresholding,
    on the 8-bit grayscale photo): it finds the quads of the pattern and orders the corners row
    by row. Corner 0 is then put at the black square's end (:func:`_orient`), so ids match
    ``board.object_points()`` in every view. The sub-pixel refinement is written here
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
    import cv2

    if not isinstance(images, ImageSet) or len(images) == 0:
        raise InvalidValue("images", "needs at least one photo")
    if not isinstance(board, Checkerboard):
        raise InvalidValue("board", f"expected a Checkerboard, got {type(board).__name__}")
    names = images.names
    grays, found_xy, found_views, warnings = [], [], [], []
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    for index, image in enumerate(images.images):
        gray = image.gray()
        gray8 = np.clip(gray * 255.0 + 0.5, 0, 255).astype(np.uint8)
        found, xy = cv2.findChessboardCorners(gray8, board.pattern_size, flags=flags)
        if not found or xy is None or len(xy) != board.num_corners:
            warnings.append(f"{names[index]}: no {board.columns}x{board.rows} board found")
            continue
        xy = _orient(gray, xy.reshape(-1, 2).astype(np.float64), board)
        grays.append(gray)
        found_xy.append(xy)
        found_views.append(index)
    if not found_views:
        raise StepFailed("images", f"no board of {board.columns}x{board.rows} inner corners was found in any of "
                                   f"the {len(images)} photos; check columns and rows (inner corners, not squares)")
    sizes = {(images[i].width, images[i].height) for i in found_views}
    if len(sizes) > 1:
        listing = ", ".join(f"{names[i]} {images[i].width}x{images[i].height}" for i in found_views)
        raise InvalidValue("images", f"the photos of one calibration must all have the same size; boards were found "
                                     f"in photos of different sizes: {listing}")
    n = board.num_corners
    xy = np.concatenate(found_xy)
    if subpixel:
        xy = refine_corners(np.stack(grays), xy, np.repeat(np.arange(len(found_views)), n), window=window)
    views = np.array(found_views, dtype=np.int64)
    corners = Points2D(xy, view=np.repeat(views, n), ids=np.tile(np.arange(n), len(views)), image="images")
    return CornerDetection(corners, board.object_points(), views, tuple(warnings), len(views), len(images))


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
    rows, which change nothing). Corresponds to ``cv2.findHomography(board_xy, pixels, 0)``.

    Args:
        normalize: apply Hartley's normalization (H&Z algorithm 4.2) before the DLT.

    Returns ``(M, 3, 3)`` with ``H[2, 2] = 1``, in the order of the sorted unique ``corners.view``.

    Reference: Hartley & Zisserman, Multiple View Geometry (2nd ed.), section 4.1 (DLT) and 4.4
    (normalization, algorithm 4.2); Zhang (2000), appendix A.
    """
    corners, board_points = _check_corners(corners, board_points)
    views, position = _views_of(corners)
    counts = np.bincount(position, minlength=len(views))
    if np.any(counts < 4):
        bad = views[counts < 4]
        raise InvalidValue("corners", f"a homography needs at least 4 points per view; view(s) {bad.tolist()} "
                                      "have fewer")
    order = np.argsort(position, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(order)) - starts[position[order]]
    size = int(counts.max())
    image_xy = np.zeros((len(views), size, 2))
    board_xy = np.zeros((len(views), size, 2))
    mask = np.zeros((len(views), size), dtype=bool)
    image_xy[position[order], slot] = corners.xy[order]
    board_xy[position[order], slot] = board_points[corners.ids[order], :2]
    mask[position[order], slot] = True
    if normalize:
        T_image, image_xy = hartley_normalization(image_xy, mask)
        T_board, board_xy = hartley_normalization(board_xy, mask)
        image_xy[~mask] = 0.0
        board_xy[~mask] = 0.0
    X, Y = board_xy[..., 0], board_xy[..., 1]
    u, v = image_xy[..., 0], image_xy[..., 1]
    one, zero = mask.astype(np.float64), np.zeros_like(X)
    rows_u = np.stack([X, Y, one, zero, zero, zero, -u * X, -u * Y, -u], axis=-1)
    rows_v = np.stack([zero, zero, zero, X, Y, one, -v * X, -v * Y, -v], axis=-1)
    A = np.concatenate([rows_u, rows_v], axis=1)  # (M, 2 size, 9)
    _, singular, Vt = np.linalg.svd(A, full_matrices=False)
    degenerate = singular[:, -2] <= 1e-10 * singular[:, 0]
    if np.any(degenerate):
        raise InvalidValue("corners", f"view(s) {views[degenerate].tolist()}: the points do not determine a "
                                      "homography (collinear or repeated points?)")
    H = Vt[:, -1].reshape(-1, 3, 3)
    if normalize:
        H = np.linalg.solve(T_image, H @ T_board)
    scale = H[:, 2, 2]
    if np.any(np.abs(scale) < 1e-12 * np.abs(H).max(axis=(1, 2))):
        raise InvalidValue("corners", "a homography maps the board origin to infinity; the input is degenerate")
    return H / scale[:, None, None]


# ----------------------------------------------------------------------------------------------------
# 3. Intrinsics (closed form)
# ----------------------------------------------------------------------------------------------------
def _v(H: np.ndarray, i: int, j: int) -> np.ndarray:
    """Zhang's ``v_ij`` (section 3.1): ``h_i^T B h_j = v_ij^T b``, ``b = (B11, B12, B22, B13, B23, B33)``."""
    hi, hj = H[:, :, i], H[:, :, j]
    return np.stack([hi[:, 0] * hj[:, 0], hi[:, 0] * hj[:, 1] + hi[:, 1] * hj[:, 0], hi[:, 1] * hj[:, 1],
                     hi[:, 2] * hj[:, 0] + hi[:, 0] * hj[:, 2], hi[:, 2] * hj[:, 1] + hi[:, 1] * hj[:, 2],
                     hi[:, 2] * hj[:, 2]], axis=-1)


def estimate_intrinsics(homographies: np.ndarray, *, zero_skew: bool = False) -> Annotated[np.ndarray, "K_init"]:
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
    H = _check_stack(homographies, "homographies", (3, 3))
    needed = 2 if zero_skew else 3
    if len(H) < needed:
        raise InvalidValue("homographies", f"Zhang's closed form needs at least {needed} views"
                                           f"{' (zero_skew)' if zero_skew else ' (or 2 with zero_skew)'}, got {len(H)}")
    H = H / np.linalg.norm(H, axis=(1, 2), keepdims=True)
    V = np.concatenate([_v(H, 0, 1), _v(H, 0, 0) - _v(H, 1, 1)], axis=0)
    if zero_skew:
        weight = 1e3 * np.linalg.norm(V, axis=1).max()
        V = np.concatenate([V, [[0.0, weight, 0.0, 0.0, 0.0, 0.0]]], axis=0)
    _, singular, Vt = np.linalg.svd(V)
    if singular[-2] <= 1e-12 * singular[0]:
        raise InvalidValue("homographies", "the views do not determine the intrinsics (boards parallel to each "
                                           "other?); tilt the board differently in each photo")
    b = Vt[-1]
    if b[0] < 0:
        b = -b
    B11, B12, B22, B13, B23, B33 = b
    denominator = B11 * B22 - B12 * B12
    if B11 <= 0 or denominator <= 0:
        raise InvalidValue("homographies", "the estimated absolute conic is not positive definite: the views "
                                           "are degenerate or too noisy")
    v0 = (B12 * B13 - B11 * B23) / denominator
    lam = B33 - (B13 * B13 + v0 * (B12 * B13 - B11 * B23)) / B11
    if lam / B11 <= 0:
        raise InvalidValue("homographies", "the estimated absolute conic is not positive definite: the views "
                                           "are degenerate or too noisy")
    alpha = np.sqrt(lam / B11)
    beta = np.sqrt(lam * B11 / denominator)
    gamma = 0.0 if zero_skew else -B12 * alpha * alpha * beta / lam
    u0 = gamma * v0 / beta - B13 * alpha * alpha / lam
    return np.array([[alpha, gamma, u0], [0.0, beta, v0], [0.0, 0.0, 1.0]])


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
    H = _check_stack(homographies, "homographies", (3, 3))
    K = as_intrinsics(K_init)
    A = np.linalg.solve(K, H)  # K^-1 H, (M, 3, 3)
    norms = 0.5 * (np.linalg.norm(A[:, :, 0], axis=1) + np.linalg.norm(A[:, :, 1], axis=1))
    if np.any(norms <= 0):
        raise InvalidValue("homographies", "a homography has a zero column")
    lam = np.sign(A[:, 2, 2]) / norms
    lam = np.where(lam == 0, 1.0 / norms, lam)
    r1 = lam[:, None] * A[:, :, 0]
    r2 = lam[:, None] * A[:, :, 1]
    t = lam[:, None] * A[:, :, 2]
    Q = np.stack([r1, r2, np.cross(r1, r2)], axis=-1)
    return Extrinsics(nearest_rotation(Q), t)


# ----------------------------------------------------------------------------------------------------
# 5. Radial distortion (linear)
# ----------------------------------------------------------------------------------------------------
def _observations(corners: Points2D, board_points: np.ndarray, count: int | None) -> tuple[np.ndarray, ...]:
    """Corners sorted by view: pixels ``(n, 2)``, board points ``(n, 3)``, view position ``(n,)``,
    image index ``(n,)``, ids ``(n,)``, and the sorted unique image indices."""
    views, position = _views_of(corners)
    if count is not None and len(views) != count:
        raise InvalidValue("corners", f"corners lie on {len(views)} views but the poses are for {count}")
    order = np.argsort(position, kind="stable")
    view = corners.view if corners.view is not None else np.zeros(len(corners), dtype=np.int64)
    return (corners.xy[order], board_points[corners.ids[order]], position[order], view[order],
            corners.ids[order], views)


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
    corners, board_points = _check_corners(corners, board_points)
    K = as_intrinsics(K_init)
    R = _check_stack(R_init, "R_init", (3, 3))
    t = _check_stack(t_init, "t_init", (3,), len(R))
    observed, points, position, *_ = _observations(corners, board_points, len(R))
    camera = np.einsum("nij,nj->ni", R[position], points) + t[position]
    if np.any(camera[:, 2] <= 0):
        raise InvalidValue("R_init", "some board corners lie behind the camera with these poses")
    x = camera[:, :2] / camera[:, 2:3]
    r2 = np.sum(x * x, axis=1)
    ideal = x @ K[:2, :2].T + K[:2, 2]
    centred = ideal - K[:2, 2]
    D = np.stack([centred * r2[:, None], centred * (r2 * r2)[:, None]], axis=-1).reshape(-1, 2)
    d = (observed - ideal).reshape(-1)
    k, *_ = np.linalg.lstsq(D, d, rcond=None)
    return np.array([k[0], k[1], 0.0, 0.0, 0.0])


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


class _Problem:
    """The reprojection residuals of all corners and their Jacobian, blocked by view.

    Parameters: ``theta`` = (fx, fy, cx, cy, skew, k1, k2, p1, p2, k3) shared by all views
    (``free`` marks those optimized), and per view ``w`` (axis-angle, 3) and ``t`` (3).
    Residual of corner ``j`` in view ``v``: ``project(K, dist, R(w_v) X_j + t_v) - x_j``.

    The corners are laid out as ``(M views, S slots)`` (views with fewer corners padded with
    rows whose residual and Jacobian are zero), so that every block of ``J^T J`` is one batched
    matrix product.
    """

    def __init__(self, observed: np.ndarray, points: np.ndarray, position: np.ndarray, num_views: int,
                 free: np.ndarray) -> None:
        counts = np.bincount(position, minlength=num_views)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        slot = np.arange(len(position)) - starts[position]  # observations are sorted by view
        size = int(counts.max())
        self.index = (position, slot)
        self.counts = counts
        self.free = free
        weight = np.zeros((num_views, size))
        weight[self.index] = 1.0
        self.weight = weight
        self.observed = np.zeros((num_views, size, 2))
        self.observed[self.index] = observed
        self.points = np.repeat(points[starts][:, None, :], size, axis=1)  # padding: a real corner, weight 0
        self.points[self.index] = points

    def residuals(self, theta: np.ndarray, w: np.ndarray, t: np.ndarray, *, jacobian: bool = False):
        """Residuals ``(M, S, 2)``; with ``jacobian`` also ``d r / d theta[free]`` ``(M, S, 2, p)`` and
        ``d r / d (w_v, t_v)`` ``(M, S, 2, 6)``."""
        fx, fy, cx, cy, s = theta[:5]
        k1, k2, p1, p2, k3 = theta[5:]
        R = rotvec_to_matrix(w)
        Y = self.points @ np.swapaxes(R, 1, 2)  # R X, (M, S, 3)
        Xc = Y + t[:, None, :]
        inv_z = 1.0 / Xc[..., 2]
        x = Xc[..., 0] * inv_z
        y = Xc[..., 1] * inv_z
        xd, yd, dxx, dxy, dyy = distort_components(x, y, theta[5:])
        weight = self.weight
        r = np.stack([(fx * xd + s * yd + cx - self.observed[..., 0]) * weight,
                      (fy * yd + cy - self.observed[..., 1]) * weight], axis=-1)
        if not jacobian:
            return r
        M, S = x.shape
        J_in = np.zeros((M, S, 2, 10))
        J_in[..., 0, 0] = xd * weight
        J_in[..., 1, 1] = yd * weight
        J_in[..., 0, 2] = weight
        J_in[..., 1, 3] = weight
        J_in[..., 0, 4] = yd * weight
        # d(x_d, y_d)/d(k1, k2, p1, p2, k3), then through A = [[fx, s], [0, fy]]
        r2 = x * x + y * y
        r4 = r2 * r2
        xy2 = 2.0 * x * y
        dx = np.stack([x * r2, x * r4, xy2, r2 + 2.0 * x * x, x * r4 * r2], axis=-1)
        dy = np.stack([y * r2, y * r4, r2 + 2.0 * y * y, xy2, y * r4 * r2], axis=-1)
        J_in[..., 0, 5:] = (fx * dx + s * dy) * weight[..., None]
        J_in[..., 1, 5:] = fy * dy * weight[..., None]
        # d(u, v)/d(Xc) = A Jd Dproj with Jd = d(x_d, y_d)/d(x, y), Dproj = d(x, y)/d(Xc)
        scale = inv_z * weight
        a00 = (fx * dxx + s * dxy) * scale
        a01 = (fx * dxy + s * dyy) * scale
        a10 = fy * dxy * scale
        a11 = fy * dyy * scale
        P = np.empty((M, S, 2, 3))
        P[..., 0, 0], P[..., 0, 1], P[..., 0, 2] = a00, a01, -(a00 * x + a01 * y)
        P[..., 1, 0], P[..., 1, 1], P[..., 1, 2] = a10, a11, -(a10 * x + a11 * y)
        # dXc/dw = -[Y]x J_left(w); a row p of P gives p (-[Y]x) = Y x p, then times J_left per view
        Yb = Y[:, :, None, :]
        cross = np.stack([Yb[..., 1] * P[..., 2] - Yb[..., 2] * P[..., 1],
                          Yb[..., 2] * P[..., 0] - Yb[..., 0] * P[..., 2],
                          Yb[..., 0] * P[..., 1] - Yb[..., 1] * P[..., 0]], axis=-1)  # (M, S, 2, 3)
        J_pose = np.empty((M, S, 2, 6))
        J_pose[..., :3] = (cross.reshape(M, 2 * S, 3) @ so3_left_jacobian(w)).reshape(M, S, 2, 3)
        J_pose[..., 3:] = P
        return r, J_in[..., self.free], J_pose

    @staticmethod
    def normal_equations(r: np.ndarray, J_in: np.ndarray, J_pose: np.ndarray) -> tuple[np.ndarray, ...]:
        """Blocks of ``J^T J`` and ``J^T r``: ``U`` (p, p), ``W`` (M, p, 6), ``V`` (M, 6, 6), ``g_in``, ``g_pose``."""
        M, p = J_in.shape[0], J_in.shape[-1]
        A = J_in.reshape(M, -1, p)
        B = J_pose.reshape(M, -1, 6)
        e = r.reshape(M, -1, 1)
        flat = A.reshape(-1, p)
        At, Bt = np.swapaxes(A, 1, 2), np.swapaxes(B, 1, 2)
        return flat.T @ flat, At @ B, Bt @ B, flat.T @ e.reshape(-1), (Bt @ e)[..., 0]


def _solve_damped(U, W, V, g_in, g_pose, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``(J^T J + damping diag(J^T J)) delta = -J^T r`` by the Schur complement on the pose blocks.

    ``S = U* - sum_v W_v V*_v^-1 W_v^T`` is the small system in the intrinsics; each view's pose
    update follows from it: ``delta_v = V*_v^-1 (-g_v - W_v^T delta_in)``.
    """
    Ud = U + damping * np.diag(np.diag(U))
    idx = np.arange(6)
    Vd = V.copy()
    Vd[:, idx, idx] *= 1.0 + damping
    V_inv = np.linalg.inv(Vd)
    WVinv = W @ V_inv  # (M, p, 6)
    S = Ud - np.einsum("mij,mkj->ik", WVinv, W)
    rhs = -g_in + np.einsum("mij,mj->i", WVinv, g_pose)
    delta_in = np.linalg.solve(S, rhs)
    delta_pose = np.einsum("mij,mj->mi", V_inv, -g_pose - np.einsum("mji,j->mi", W, delta_in))
    return delta_in, delta_pose


def _rms_colors(values: np.ndarray) -> np.ndarray:
    """Green (smallest) to red (largest) for each value, ``(N, 3)``."""
    values = np.asarray(values, dtype=np.float64)
    span = values.max() - values.min() if len(values) else 0.0
    level = (values - values.min()) / span if span > 0 else np.zeros(len(values))
    return np.stack([0.15 + 0.8 * level, 0.75 - 0.65 * level, 0.2 - 0.1 * level], axis=1)


def _board_mesh(board: Checkerboard | None, board_points: np.ndarray) -> Mesh:
    if isinstance(board, Checkerboard):
        return board.mesh()
    lo, hi = board_points[:, :2].min(axis=0), board_points[:, :2].max(axis=0)
    vertices = np.array([[lo[0], lo[1], 0.0], [hi[0], lo[1], 0.0], [hi[0], hi[1], 0.0], [lo[0], hi[1], 0.0]])
    return Mesh(vertices, np.array([[0, 1, 2], [0, 2, 3]]), np.full((4, 3), 0.8))


def refine_calibration(corners: Points2D, board_points: np.ndarray, K_init: np.ndarray, dist_init: np.ndarray,
                       R_init: np.ndarray, t_init: np.ndarray, images: ImageSet | None = None,
                       board: Checkerboard | None = None, *, estimate_skew: bool = False, fix_k3: bool = False,
                       fix_tangential: bool = False, max_iterations: Annotated[int, Range(1, 500)] = 100,
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
    corners, board_points = _check_corners(corners, board_points)
    K0 = as_intrinsics(K_init)
    dist0 = as_distortion(dist_init)
    R0 = _check_stack(R_init, "R_init", (3, 3))
    t0 = _check_stack(t_init, "t_init", (3,), len(R0))
    observed, points, position, image_index, ids, views = _observations(corners, board_points, len(R0))
    free = np.array([True, True, True, True, estimate_skew, True, True, not fix_tangential, not fix_tangential,
                     not fix_k3])
    num_free = int(free.sum()) + 6 * len(views)
    if 2 * len(observed) <= num_free:
        raise InvalidValue("corners", f"{len(observed)} corners give {2 * len(observed)} equations, not enough for "
                                      f"{num_free} parameters; use more views or more corners")
    theta = np.array([K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2], K0[0, 1], *dist0])
    theta[~free] = 0.0
    w = matrix_to_rotvec(R0)
    t = t0.copy()
    problem = _Problem(observed, points, position, len(views), free)
    r, J_in, J_pose = problem.residuals(theta, w, t, jacobian=True)
    cost = float(np.sum(r * r))
    if not np.isfinite(cost):
        raise InvalidValue("K_init", "the initial parameters put board corners behind the camera")
    n_points = len(observed)
    history = [np.sqrt(cost / n_points)]
    damping = 1e-3
    iterations = 0
    for iterations in range(1, int(max_iterations) + 1):
        U, W, V, g_in, g_pose = problem.normal_equations(r, J_in, J_pose)
        try:
            delta_in, delta_pose = _solve_damped(U, W, V, g_in, g_pose, damping)
        except np.linalg.LinAlgError:
            raise StepFailed("refine_calibration", "the normal equations are singular: the views do not "
                                                   "constrain the parameters (too few or parallel views?)") from None
        theta_new = theta.copy()
        theta_new[free] += delta_in
        w_new = w + delta_pose[:, :3]
        t_new = t + delta_pose[:, 3:]
        r_new = problem.residuals(theta_new, w_new, t_new)
        cost_new = float(np.sum(r_new * r_new))
        step = np.sqrt(np.sum(delta_in**2) + np.sum(delta_pose**2))
        size = np.sqrt(np.sum(theta[free] ** 2) + np.sum(w**2) + np.sum(t**2))
        converged = False
        if np.isfinite(cost_new) and cost_new < cost:
            converged = (cost - cost_new) <= 1e-10 * cost or step <= 1e-10 * size
            theta, w, t, cost = theta_new, w_new, t_new, cost_new
            r, J_in, J_pose = problem.residuals(theta, w, t, jacobian=True)
            damping = max(damping / 10.0, 1e-12)
        else:
            damping *= 10.0
            converged = damping > 1e12 or step <= 1e-12 * size
        history.append(np.sqrt(cost / n_points))
        preview = Points2D(observed + r[problem.index], view=image_index, ids=ids, image="images")
        yield Progress(iteration=iterations, total=int(max_iterations), loss=history[-1],
                       message=f"RMS {history[-1]:.5f} px, lambda {damping:.1e}", values={"reprojected": preview})
        if converged:
            break

    # uncertainties from the Jacobian at the solution
    U, W, V, _, _ = problem.normal_equations(r, J_in, J_pose)
    std = np.zeros(10)
    try:
        S = U - np.einsum("mij,mkj->ik", W @ np.linalg.inv(V), W)
        sigma2 = cost / (2 * n_points - num_free)
        std[free] = np.sqrt(np.maximum(np.diag(np.linalg.pinv(S)), 0.0) * sigma2)
    except np.linalg.LinAlgError:
        std[:] = np.nan

    K = np.array([[theta[0], theta[4], theta[2]], [0.0, theta[1], theta[3]], [0.0, 0.0, 1.0]])
    dist = theta[5:].copy()
    rotations = rotvec_to_matrix(w)
    per_view = np.sqrt(np.sum(r * r, axis=(1, 2)) / problem.counts)
    r = r[problem.index]  # (n, 2), in the order of the observations
    squared = np.sum(r * r, axis=1)
    worst = int(np.argmax(per_view))
    names = images.names if isinstance(images, ImageSet) else tuple(f"view {i}" for i in range(int(views.max()) + 1))
    view_names = tuple(names[i] if i < len(names) else f"view {i}" for i in views)
    if isinstance(images, ImageSet) and len(images):
        width, height = images[0].width, images[0].height
    else:
        width, height = max(1, int(round(2 * K[0, 2] + 1))), max(1, int(round(2 * K[1, 2] + 1)))
    colors = _rms_colors(per_view)
    cameras = Cameras(K=np.broadcast_to(K, (len(views), 3, 3)).copy(), R=rotations, t=t, width=width, height=height,
                      dist=dist, image="images", views=views, colors=colors)
    reprojected_xy = observed + r
    magnitude = np.sqrt(squared)
    residuals = Segments2D(observed, observed + residual_scale * r, view=image_index,
                           colors=_rms_colors(magnitude), image="images")
    per_view_curve = Curve(np.arange(len(views), dtype=np.float64), per_view, kind="bar",
                           title=f"RMS reprojection error per view (worst: {view_names[worst]}, "
                                 f"{per_view[worst]:.3f} px)",
                           xlabel="view", ylabel="RMS (px)", labels=("RMS",), categories=view_names)
    cost_curve = Curve(np.arange(len(history), dtype=np.float64), np.array(history), kind="line",
                       title="Levenberg-Marquardt", xlabel="iteration", ylabel="RMS reprojection error (px)",
                       labels=("RMS",))
    rms = float(np.sqrt(cost / n_points))
    return Calibration(
        K=K, dist=dist, rotations=rotations, translations=t, cameras=cameras,
        board_mesh=_board_mesh(board, board_points),
        reprojected=Points2D(reprojected_xy, view=image_index, ids=ids, image="images"), residuals=residuals,
        per_view_rms=per_view_curve, std_intrinsics=std, cost=cost_curve, rms_px=rms,
        fx=theta[0], fy=theta[1], cx=theta[2], cy=theta[3], skew=theta[4], k1=theta[5], k2=theta[6], p1=theta[7],
        p2=theta[8], k3=theta[9], fx_std=std[0], fy_std=std[1], cx_std=std[2], cy_std=std[3], skew_std=std[4],
        k1_std=std[5], k2_std=std[6], p1_std=std[7], p2_std=std[8], k3_std=std[9],
        per_view_rms_px=[float(v) for v in per_view], worst_view=int(views[worst]), iterations=iterations)


# ----------------------------------------------------------------------------------------------------
# 7. Undistortion
# ----------------------------------------------------------------------------------------------------
def undistort_image(images: ImageSet, K: np.ndarray, dist: np.ndarray, *, view: Annotated[int, Range(0, None)] = 0,
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


# ----------------------------------------------------------------------------------------------------
# Evaluations (run after a step; truth may be empty)
# ----------------------------------------------------------------------------------------------------
def _truth_views(state: dict[str, Any]) -> np.ndarray:
    return _views_of(state["corners"])[0]


def _intrinsic_errors(K: np.ndarray, truth: dict[str, Any]) -> dict[str, float]:
    T = np.asarray(truth["K"])
    return {"fx_rel_error": abs(K[0, 0] - T[0, 0]) / T[0, 0], "fy_rel_error": abs(K[1, 1] - T[1, 1]) / T[1, 1],
            "cx_rel_error": abs(K[0, 2] - T[0, 2]) / T[0, 2], "cy_rel_error": abs(K[1, 2] - T[1, 2]) / T[1, 2],
            "skew_abs_error": abs(K[0, 1] - T[0, 1])}


def _pose_errors(R: np.ndarray, t: np.ndarray, views: np.ndarray, truth: dict[str, Any]) -> dict[str, float]:
    R_true = np.asarray(truth["rotations"])[views]
    t_true = np.asarray(truth["translations"])[views]
    angles = rotation_angle_deg(R, R_true)
    rel = np.linalg.norm(t - t_true, axis=1) / np.linalg.norm(t_true, axis=1)
    return {"rotation_error_deg": float(angles.mean()), "rotation_error_max_deg": float(angles.max()),
            "translation_rel_error": float(rel.mean())}


def evaluate_homographies(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``transfer_rms_px``: RMS distance between the detected corners and the board mapped by H (no truth needed)."""
    corners, board_points, H = state["corners"], state["board_points"], state["homographies"]
    _, position = _views_of(corners)
    mapped = apply_homography(np.asarray(H)[position], board_points[corners.ids][:, None, :2])[:, 0]
    return {"transfer_rms_px": float(np.sqrt(np.mean(np.sum((mapped - corners.xy) ** 2, axis=1))))}


def evaluate_intrinsics(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Relative errors of ``K_init`` against the true ``K``."""
    return _intrinsic_errors(np.asarray(state["K_init"]), truth) if "K" in truth else {}


def evaluate_extrinsics(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Rotation angle error (degrees) and relative translation error of the closed-form poses."""
    if "rotations" not in truth:
        return {}
    return _pose_errors(state["R_init"], state["t_init"], _truth_views(state), truth)


def evaluate_distortion(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Absolute errors of the linear ``k1, k2``."""
    if "dist" not in truth:
        return {}
    d, T = np.asarray(state["dist_init"]), np.asarray(truth["dist"])
    return {"k1_abs_error": abs(d[0] - T[0]), "k2_abs_error": abs(d[1] - T[1])}


def evaluate_refinement(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Errors of the refined intrinsics, distortion and poses; ``truth_rms_px``: RMS distance between
    the reprojected corners and the exact (noise-free) projections."""
    if "K" not in truth:
        return {}
    out = _intrinsic_errors(np.asarray(state["K"]), truth)
    d, T = np.asarray(state["dist"]), np.asarray(truth["dist"])
    out.update({f"{name}_abs_error": abs(d[i] - T[i]) for i, name in enumerate(("k1", "k2", "p1", "p2", "k3"))})
    out.update(_pose_errors(state["rotations"], state["translations"], _truth_views(state), truth))
    if "corners" in truth:
        reprojected, exact = state["reprojected"], truth["corners"]
        n = int(exact.ids.max()) + 1
        lookup = {int(v) * n + int(i): k for k, (v, i) in enumerate(zip(exact.view, exact.ids))}
        index = np.array([lookup[int(v) * n + int(i)] for v, i in zip(reprojected.view, reprojected.ids)])
        diff = reprojected.xy - exact.xy[index]
        out["truth_rms_px"] = float(np.sqrt(np.mean(np.sum(diff * diff, axis=1))))
    return out


PIPELINE = Pipeline.build(
    name="calibration",
    title="Camera calibration",
    summary="Zhang's method step by step: detect the corners of a checkerboard, fit a homography per view, "
            "solve for the intrinsics and poses in closed form, estimate radial distortion, refine everything "
            "by Levenberg-Marquardt, and undistort a photo.",
    steps=[detect_corners, estimate_homographies, estimate_intrinsics, estimate_extrinsics, estimate_distortion,
           refine_calibration, undistort_image],
    datasets=[synthetic, folder],
    evaluations={"estimate_homographies": evaluate_homographies, "estimate_intrinsics": evaluate_intrinsics,
                 "estimate_extrinsics": evaluate_extrinsics, "estimate_distortion": evaluate_distortion,
                 "refine_calibration": evaluate_refinement},
)

__all__ = ["PIPELINE", "INTRINSIC_NAMES", "CornerDetection", "Extrinsics", "Calibration", "detect_corners",
           "refine_corners", "estimate_homographies", "estimate_intrinsics", "estimate_extrinsics",
           "estimate_distortion", "refine_calibration", "undistort_image", "evaluate_homographies",
           "evaluate_intrinsics", "evaluate_extrinsics", "evaluate_distortion", "evaluate_refinement"]
