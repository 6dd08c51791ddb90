"""The datasets of calibration: a synthetic checkerboard with exact truth, and a user's folder of photos.

The synthetic generator (:func:`synthetic`) renders the board printed on white paper, seen by a
camera with known ``K``, OpenCV distortion and poses, anti-aliased exactly, slightly blurred, with
corners displaced by a controlled amount of noise and a little pixel noise
(:mod:`lab.modules.calibration.rendering`); its truth holds the exact ``K``, distortion, poses and
projections of every corner; with partial boards (``missing_corners``, ``shuffle_corners``) it also gives
the corners a detector of partial boards would report (:func:`partial_corners`). Both datasets give
the state ``images`` (ImageSet) and ``board`` (:class:`~lab.modules.calibration.board.Checkerboard`).
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np

from lab.core import Image, ImageSet, InvalidValue, Loaded, Points2D, Range
from lab.core.budgets import check_dataset_pixels
from lab.data.files import WORKING_SIDE
from lab.geometry.camera import as_distortion, project_points
from lab.geometry.rotations import rotvec_to_matrix
from lab.modules.calibration.board import Checkerboard
from lab.modules.calibration.rendering import PixelRays, board_displacements, render_view

#: Range of the paper's width as a fraction of the image width, and how far (as a fraction of the image
#: size) the board's centre may move from the principal point: large boards all over the image
#: constrain the principal point and the distortion best.
_PAPER_FRACTION = (0.7, 0.95)
_JITTER = 0.3


def synthetic(*, columns: Annotated[int, Range(3, 20)] = 9, rows: Annotated[int, Range(3, 20)] = 6,
              square_size: Annotated[float, Range(0.001, 1.0)] = 0.025,
              num_views: Annotated[int, Range(3, 60)] = 15,
              width: Annotated[int, Range(160, 4096)] = 640, height: Annotated[int, Range(120, 4096)] = 480,
              fx: Annotated[float, Range(50.0, 20000.0)] = 350.0,
              fy: Annotated[float, Range(50.0, 20000.0)] = 347.0,
              cx: Annotated[float, Range(0.0, 4096.0)] = 318.0,
              cy: Annotated[float, Range(0.0, 4096.0)] = 242.0,
              k1: Annotated[float, Range(-1.0, 1.0)] = -0.25, k2: Annotated[float, Range(-1.0, 1.0)] = 0.08,
              p1: Annotated[float, Range(-0.05, 0.05)] = 0.0008,
              p2: Annotated[float, Range(-0.05, 0.05)] = -0.0006,
              k3: Annotated[float, Range(-1.0, 1.0)] = 0.0,
              pose_spread_deg: Annotated[float, Range(5.0, 65.0)] = 40.0,
              noise_px: Annotated[float, Range(0.0, 5.0)] = 0.2,
              blur_px: Annotated[float, Range(0.0, 3.0)] = 0.7,
              image_noise: Annotated[float, Range(0.0, 0.2)] = 0.01,
              color: bool = False, missing_corners: Annotated[float, Range(0.0, 0.8)] = 0.0,
              shuffle_corners: bool = False, seed: int = 0) -> Loaded:
    """A checkerboard seen by a camera with known intrinsics, distortion and poses (exact ground truth).

    Each view tilts the board by 50 to 100 % of ``pose_spread_deg`` about an axis in its plane
    (the axes spread evenly around the circle, as Zhang's method needs non-parallel views),
    turns it in its plane by up to half that, and places it so that the whole paper lies inside
    the image. Each image is rendered by following every pixel's ray: undistort its coordinate
    (Newton's method), intersect the ray with the board plane, and average the printed pattern
    exactly over the pixel's footprint on the board (anti-aliasing by an analytic box filter,
    which supersampling approximates: 4 x 4 samples quantize an edge aligned with the pixel grid
    to a quarter pixel); then blur by the lens's point spread function (a Gaussian of
    ``blur_px``), which real photos have and which ``cv2.cornerSubPix`` needs to be unbiased.

    Corner noise: each corner ``i`` gets an image displacement ``d_i ~ N(0, noise_px^2)`` per
    axis. The displacements are turned into board coordinates (through the local Jacobian of the
    projection) and interpolated bilinearly over the corner grid into a smooth field ``D``; a
    pixel shows the board at ``b(x) - D(b(x))``, so corner ``i`` appears at ``p_i + d_i`` while the
    truth keeps the exact projection ``p_i``. Then Gaussian pixel noise of ``image_noise``.
    Rendering 15 views of 640 x 480 takes about a second.

    Partial boards (``missing_corners > 0`` or ``shuffle_corners``): the dataset also gives the
    corners, as a detector of partial boards (ChArUco's, say) reports them, so that
    ``detect_corners`` (which finds whole boards only) is not needed: each corner at ``p_i + d_i``
    (where the photo shows it) with its board id, every corner of a view left out with probability
    ``missing_corners`` (at least 8 kept per view), and with ``shuffle_corners`` all of them in a
    random order, the views interleaved. The photos and the truth are those of the same seed
    without these options; running ``detect_corners`` again replaces the corners with the whole
    boards it finds.

    Args:
        columns: inner corners per row of the board.
        rows: inner corners per column of the board.
        square_size: side of a square in metres.
        num_views: number of photos.
        width: image width in pixels.
        height: image height in pixels.
        fx: focal length along x in pixels.
        fy: focal length along y in pixels.
        cx: principal point x in pixels.
        cy: principal point y in pixels.
        k1: radial distortion (r^2).
        k2: radial distortion (r^4).
        p1: tangential distortion.
        p2: tangential distortion.
        k3: radial distortion (r^6).
        pose_spread_deg: largest tilt of the board away from facing the camera, in degrees.
        noise_px: standard deviation of each corner's displacement per axis, in pixels.
        blur_px: standard deviation of the lens blur in pixels (0: none).
        image_noise: standard deviation of the pixel noise (intensities in [0, 1]).
        color: render RGB images (tinted paper and background) instead of grayscale.
        missing_corners: probability that a corner is left out of a view's corners (partial boards;
            the dataset then gives the corners).
        shuffle_corners: give the corners in a random order, views interleaved (the dataset then
            gives the corners).
        seed: random seed of the poses and the noise.

    Truth: ``K`` (3, 3), ``dist`` (5,), ``rotations`` (V, 3, 3), ``translations`` (V, 3) (board to
    camera), ``corners`` (Points2D of the exact projections of every corner, ``view`` and ``ids`` set).
    With partial boards the state also holds ``corners``, ``board_points`` and ``views``.
    """
    import cv2

    check_dataset_pixels(views=num_views, width=width, height=height)
    board = Checkerboard(columns, rows, square_size)
    if not (0 <= cx < width and 0 <= cy < height):
        raise InvalidValue("cx", f"the principal point ({cx}, {cy}) must lie inside the "
                                 f"{width}x{height} image")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    dist = as_distortion([k1, k2, p1, p2, k3])
    rng = np.random.default_rng(seed)
    pixel_grid = PixelRays(K, dist, width, height)
    R, t = sample_poses(board, K, dist, width, height, num_views, pose_spread_deg, rng)
    points = board.object_points()
    exact = project_points(points[None], K, dist, R, t)  # (V, N, 2)
    displacement = rng.normal(0.0, noise_px, exact.shape) if noise_px > 0 else np.zeros(exact.shape)
    images = []
    for v in range(num_views):
        board_shift = board_displacements(board, K, dist, R[v], t[v], displacement[v]).astype(np.float32)
        pixels = render_view(board, pixel_grid, K, dist, R[v], t[v], board_shift, color=color)
        if blur_px > 0:
            pixels = cv2.GaussianBlur(pixels, (0, 0), blur_px, borderType=cv2.BORDER_REPLICATE)
        if image_noise > 0:
            pixels = pixels + rng.normal(0.0, image_noise, pixels.shape)
        images.append(Image(np.clip(pixels, 0.0, 1.0).astype(np.float32), name=f"view {v:02d}"))
    n = board.num_corners
    truth_corners = Points2D(exact.reshape(-1, 2), view=np.repeat(np.arange(num_views), n),
                             ids=np.tile(np.arange(n), num_views), image="images")
    truth = {"K": K, "dist": dist, "rotations": R, "translations": t, "corners": truth_corners}
    description = (f"Synthetic: a {columns}x{rows} board ({square_size * 1000:g} mm squares) in {num_views} "
                   f"views of {width}x{height} px, fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g}, "
                   f"k1={k1:g} k2={k2:g} p1={p1:g} p2={p2:g} k3={k3:g}, corner noise {noise_px:g} px")
    state: dict[str, Any] = {"images": ImageSet(tuple(images)), "board": board}
    if missing_corners > 0 or shuffle_corners:
        seen = Points2D((exact + displacement).reshape(-1, 2), view=truth_corners.view, ids=truth_corners.ids,
                        image="images")
        state.update(corners=partial_corners(seen, missing=missing_corners, shuffle=shuffle_corners,
                                             rng=np.random.default_rng([seed, _PARTIAL_STREAM])),
                     board_points=board.object_points(), views=np.arange(num_views, dtype=np.int64))
        description += (f"; partial boards: each corner missing with probability {missing_corners:g}"
                        + (", in random order" if shuffle_corners else ""))
    return Loaded(state, truth, description)


#: The random stream of :func:`partial_corners` (apart from the poses' and the noise's, so the photos of a
#: seed are the same with and without partial boards).
_PARTIAL_STREAM = 0xC0DE
#: Fewest corners a view keeps with ``missing_corners`` (a homography needs 4; 8 keep it well determined).
MIN_CORNERS_KEPT = 8


def partial_corners(corners: Points2D, *, missing: float, shuffle: bool,
                    rng: np.random.Generator) -> Points2D:
    """``corners`` as a detector of partial boards reports them: each left out with probability ``missing``
    (at least :data:`MIN_CORNERS_KEPT` kept per view, chosen at random), with ``shuffle`` in a random order
    (the views interleaved); every corner keeps its view and board id."""
    view = np.asarray(corners.view)
    keep = rng.random(len(view)) >= missing
    for v in np.unique(view):
        mine = np.flatnonzero(view == v)
        if keep[mine].sum() < MIN_CORNERS_KEPT:
            keep[rng.choice(mine, size=min(MIN_CORNERS_KEPT, len(mine)), replace=False)] = True
    order = np.flatnonzero(keep)
    if shuffle:
        order = rng.permutation(order)
    ids = np.asarray(corners.ids)
    return Points2D(corners.xy[order], view=view[order], ids=ids[order], image=corners.image)


def sample_poses(board: Checkerboard, K: np.ndarray, dist: np.ndarray, width: int, height: int,
                 num_views: int, spread_deg: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Board-to-camera poses ``R`` (V, 3, 3), ``t`` (V, 3) with the whole paper inside the image."""
    s = board.square_size
    centre = np.array([(board.columns - 1) * s / 2, (board.rows - 1) * s / 2, 0.0])
    outline = board.paper_outline()
    paper_width = (board.columns + 3) * s
    spread = np.radians(spread_deg)
    phase = rng.uniform(0, 2 * np.pi)
    rotations, translations = [], []
    border = 3.0
    for v in range(num_views):
        for _attempt in range(500):
            phi = phase + 2 * np.pi * (v + rng.uniform(-0.3, 0.3)) / num_views
            tilt = spread * rng.uniform(0.5, 1.0)
            roll = spread * rng.uniform(-0.5, 0.5)
            R = rotvec_to_matrix(tilt * np.array([np.cos(phi), np.sin(phi), 0.0])) \
                @ rotvec_to_matrix(np.array([0.0, 0.0, roll]))
            fraction = rng.uniform(*_PAPER_FRACTION) * 0.99**_attempt  # smaller boards after failed tries
            depth = K[0, 0] * paper_width / (fraction * width)
            target = K[:2, 2] + rng.uniform(-1, 1, 2) * _JITTER * np.array([width, height])
            ray = np.linalg.solve(K, np.append(target, 1.0))
            t = depth * ray - R @ centre
            camera_points = outline @ R.T + t
            if np.min(camera_points[:, 2]) <= 1e-3 * depth:
                continue
            pixels = project_points(outline, K, dist, R, t)
            if np.all(np.isfinite(pixels)) and np.all(pixels >= border) \
                    and np.all(pixels[:, 0] <= width - 1 - border) \
                    and np.all(pixels[:, 1] <= height - 1 - border):
                rotations.append(R)
                translations.append(t)
                break
        else:
            raise InvalidValue("pose_spread_deg", "could not place the board inside the image in 500 tries; "
                                                  "lower pose_spread_deg or the focal lengths")
    return np.array(rotations), np.array(translations)


def folder(*, path: str, columns: Annotated[int, Range(2, 100)] = 9, rows: Annotated[int, Range(2, 100)] = 6,
           square_size: Annotated[float, Range(1e-6, 100.0)] = 0.025, pattern: str = "*",
           max_side: Annotated[int, Range(0, 16384)] = WORKING_SIDE) -> Loaded:
    """A folder of checkerboard photos (any format OpenCV reads), sorted by file name; no truth.

    Photos larger than the working size are read at it (:func:`lab.data.files.read_working_images`):
    the calibration's K is then that of the working-size images (the description says so; for the
    files' pixels use :func:`lab.geometry.camera.scale_intrinsics` with ``1 / scale``, or
    ``max_side=0``).

    Args:
        path: the folder that holds the photos.
        columns: inner corners per row of the board.
        rows: inner corners per column of the board.
        square_size: side of a square in metres.
        pattern: shell pattern of the file names to read (e.g. ``left*.jpg``); files that are not
            images are skipped.
        max_side: read the photos at a working size whose longer side is at most this many pixels
            (:data:`lab.data.files.WORKING_SIDE`; 0: full resolution).
    """
    from lab.data.files import IMAGE_SUFFIXES, list_images, read_working_images

    board = Checkerboard(columns, rows, square_size)
    files = list_images(path, pattern)
    if not files:
        raise InvalidValue("path", f"folder {path!r} holds no images matching {pattern!r} "
                                   f"(readable endings: {', '.join(IMAGE_SUFFIXES)})")
    read = read_working_images(files, max_side=int(max_side))
    description = (f"{len(read.images)} photos from {path} ({columns}x{rows} inner corners, "
                   f"{square_size * 1000:g} mm squares)")
    if read.note:
        description += f"; {read.note}: K is estimated for the working size"
    return Loaded({"images": ImageSet(read.images), "board": board}, {}, description)


__all__ = ["MIN_CORNERS_KEPT", "folder", "partial_corners", "sample_poses", "synthetic"]
