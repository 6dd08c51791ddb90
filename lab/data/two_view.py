"""Two-view datasets for epipolar geometry: synthetic scenes with exact truth, and a user's pair of photos.

Every dataset seeds the state the epipolar module reads (see ``lab/modules/epipolar.py``):
``images`` (an ImageSet of two) and the camera matrices ``K1``, ``K2`` (3, 3); the synthetic
correspondences also seed the feature and match values, so the pipeline may start at the
estimators. Conventions (DESIGN.md section 3): camera 1 is the world frame (``R1 = I``,
``t1 = 0``); camera 2 sees ``X_2 = R X_1 + t``; ``x2^T F x1 = 0``; ``E = [t]_x R`` and
``F = K2^-T E K1^-1``.

* :func:`correspondences` - random 3D points projected through two known cameras: exact truth,
  controlled noise and outliers, and degenerate configurations on demand (all points on one
  plane or one line, zero baseline). Its images show each point as a coloured dot, and each
  point gets a random descriptor shared by its two views, so the matching step finds exactly
  the generated matches (outliers included).
* :func:`rendered` - a textured scene of :mod:`lab.data.scenes` rendered from two cameras with
  exact ``R``, ``t``, ``K`` and depth, for the whole pipeline from SIFT on.
* :func:`photos` - a folder with two photos and, optionally, their camera matrix (a file in the
  format of OpenCV's ``essential_mat_data.txt``, or ``fx, fy, cx, cy``); no truth.
"""

from __future__ import annotations

import os
from typing import Annotated, Literal

import numpy as np

from lab.core import Image, ImageSet, InvalidValue, Loaded, Points2D, Range
from lab.core.budgets import check_dataset_pixels
from lab.data.files import check_folder, list_images, read_images
from lab.geometry.two_view import fundamental_from_pose
from lab.geometry.camera import project_points
from lab.geometry.rotations import look_at, rotvec_to_matrix, skew

#: Length of the synthetic descriptors (SIFT's).
DESCRIPTOR_SIZE = 128


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _line_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Distance (px) of each ``x2`` from its epipolar line ``F x1``, ``(N,)`` (to place the outliers)."""
    lines = np.column_stack([x1, np.ones(len(x1))]) @ F.T
    return np.abs(np.sum(lines[:, :2] * x2, axis=1) + lines[:, 2]) / np.linalg.norm(lines[:, :2], axis=1)


# ----------------------------------------------------------------------------------------------------
# Synthetic correspondences
# ----------------------------------------------------------------------------------------------------
def relative_pose(baseline: float, distance: float, rng: np.random.Generator, *,
                  jitter_deg: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Camera 2 at ``baseline`` from camera 1 (mostly sideways), turned towards the point ``(0, 0, distance)``.

    The direction of the baseline is random, within 30 degrees of the image plane's x axis (either
    side) and tilted up or down by at most 15 degrees; on top of looking at the scene centre the
    camera is turned by a random rotation of at most ``jitter_deg`` degrees. With ``baseline = 0``
    the two cameras share a centre (a pure rotation). Returns ``R`` (3, 3), ``t`` (3,) with
    ``X_2 = R X_1 + t`` and ``|t| = baseline``.
    """
    azimuth = rng.uniform(-np.pi / 6, np.pi / 6) + (np.pi if rng.random() < 0.5 else 0.0)
    elevation = rng.uniform(-np.pi / 12, np.pi / 12)
    direction = np.array([np.cos(elevation) * np.cos(azimuth), np.sin(elevation),
                          np.cos(elevation) * np.sin(azimuth)])
    centre = baseline * direction
    target = np.array([0.0, 0.0, distance])
    R_look, _ = look_at(centre, target)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R = rotvec_to_matrix(np.radians(rng.uniform(0.5, 1.0) * jitter_deg) * axis) @ R_look
    t = -R @ centre
    return R, t


def _sample_structure(structure: str, count: int, distance: float, depth_range: float, half_width: float,
                      half_height: float, rng: np.random.Generator) -> np.ndarray:
    """``count`` candidate 3D points (camera-1 frame) of the requested structure, ``(count, 3)``."""
    if structure == "volume":
        z = rng.uniform(distance - depth_range / 2, distance + depth_range / 2, count)
        x = rng.uniform(-1, 1, count) * half_width * z / distance
        y = rng.uniform(-1, 1, count) * half_height * z / distance
        return np.column_stack([x, y, z])
    centre = np.array([0.0, 0.0, distance])
    if structure == "plane":  # a plane through the scene centre, tilted 20-40 degrees from fronto-parallel
        tilt = np.radians(rng.uniform(20, 40))
        phi = rng.uniform(0, 2 * np.pi)
        normal = np.array([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), -np.cos(tilt)])
        u = np.cross(normal, [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        a, b = rng.uniform(-1.5, 1.5, (2, count))
        return centre + a[:, None] * u * half_width + b[:, None] * v * half_width
    # "line": a 3D line through the scene centre, oblique to the image plane
    direction = np.array([1.0, rng.uniform(-0.5, 0.5), rng.uniform(0.3, 0.8)])
    direction /= np.linalg.norm(direction)
    s = rng.uniform(-1.5, 1.5, count) * half_width
    return centre + s[:, None] * direction


def _dot_image(xy: np.ndarray, colors: np.ndarray, width: int, height: int, name: str) -> Image:
    """A grey image with a filled disc of radius 3 px at each point, in the point's colour."""
    import cv2

    canvas = np.full((height, width, 3), 0.35, dtype=np.float32)
    for (x, y), color in zip(np.round(xy * 4).astype(int), colors.astype(np.float32)):
        cv2.circle(canvas, (int(x), int(y)), 12, tuple(float(c) for c in color), thickness=-1,
                   lineType=cv2.LINE_AA, shift=2)
    return Image(canvas, name=name)


def correspondences(*, num_points: Annotated[int, Range(8, 20000)] = 400,
                    baseline: Annotated[float, Range(0.0, 20.0)] = 1.0,
                    noise_px: Annotated[float, Range(0.0, 20.0)] = 0.5,
                    outlier_rate: Annotated[float, Range(0.0, 0.9)] = 0.3,
                    structure: Literal["volume", "plane", "line"] = "volume",
                    distance: Annotated[float, Range(0.5, 1000.0)] = 5.0,
                    depth_range: Annotated[float, Range(0.0, 1000.0)] = 4.0,
                    width: Annotated[int, Range(32, 4096)] = 640, height: Annotated[int, Range(32, 4096)] = 480,
                    fx: Annotated[float, Range(10.0, 1e5)] = 600.0, fy: Annotated[float, Range(10.0, 1e5)] = 600.0,
                    cx: float = 319.5, cy: float = 239.5, seed: int = 0) -> Loaded:
    """Random 3D points seen by two known cameras: exact truth, Gaussian noise and wrong matches.

    Camera 1 is the world frame; camera 2 stands ``baseline`` away (mostly sideways) and looks at the
    scene centre ``(0, 0, distance)`` (:func:`relative_pose`). Points fill the part of camera 1's
    view between depths ``distance -+ depth_range / 2`` and are kept only where both cameras see them
    (a 4 px border). Both observations get independent Gaussian noise of ``noise_px`` per axis; then
    a fraction ``outlier_rate`` of the matches is replaced by a wrong point in image 2, drawn
    uniformly over the image but at least 10 px from its true epipolar line (and from
    the true point), so it is unambiguously an outlier.

    ``structure`` "plane" puts all points on one tilted plane and "line" on one 3D line, and
    ``baseline = 0`` makes a pure rotation: the degenerate inputs for which F is not determined.

    Args:
        num_points: number of matches.
        baseline: distance between the camera centres (the scene is at ``distance``).
        noise_px: standard deviation of the pixel noise per axis on both images.
        outlier_rate: fraction of the matches that are wrong.
        structure: "volume" (a general scene), "plane" or "line" (degenerate).
        distance: depth of the scene centre in camera 1.
        depth_range: depth extent of the points (volume).
        width: image width in pixels.
        height: image height in pixels.
        fx: focal length along x in pixels (both cameras).
        fy: focal length along y in pixels.
        cx: principal point x in pixels.
        cy: principal point y in pixels.
        seed: random seed of the scene, the noise and the outliers.

    State: ``images`` (dots), ``K1``, ``K2``, ``keypoints`` (Points2D, view 0 then view 1),
    ``descriptors`` (2M, 128), ``matches`` (M, 2) (keypoint ``i`` of view 0 with ``M + i``), ``x1``,
    ``x2`` (M, 2). Truth: ``K1``, ``K2``, ``R``, ``t`` (``|t| = baseline``), ``F`` (unit norm), ``E``
    (``[t/|t|]_x R``), ``points3d`` (M, 3) in camera 1's frame, ``x1_exact``, ``x2_exact`` (the
    noise-free projections), ``outliers`` (M,) bool, ``keypoint_track`` (2M,) the point each
    keypoint observes (-1 for an outlier's wrong point).
    """
    if num_points < 8:
        raise InvalidValue("num_points", f"needs at least 8 matches, got {num_points}")
    if not (0 <= cx < width and 0 <= cy < height):
        raise InvalidValue("cx", f"the principal point ({cx}, {cy}) must lie inside the {width}x{height} image")
    if structure == "volume" and depth_range >= 2 * distance:
        raise InvalidValue("depth_range", f"must be less than twice the distance ({2 * distance:g}) so that every "
                                          "point lies in front of camera 1")
    rng = np.random.default_rng(seed)
    K = intrinsics(fx, fy, cx, cy)
    R, t = relative_pose(baseline, distance, rng)
    half_width = distance * max(cx, width - 1 - cx) / fx
    half_height = distance * max(cy, height - 1 - cy) / fy
    border = 4.0
    points = np.zeros((0, 3))
    for _attempt in range(50):
        candidates = _sample_structure(structure, 4 * num_points, distance, depth_range, half_width, half_height,
                                       rng)
        depth2 = candidates @ R[2] + t[2]
        p1 = project_points(candidates, K, None, np.eye(3), np.zeros(3))
        p2 = project_points(candidates, K, None, R, t)
        inside = (candidates[:, 2] > 1e-3 * distance) & (depth2 > 1e-3 * distance)
        for p in (p1, p2):
            inside &= (p[:, 0] >= border) & (p[:, 0] <= width - 1 - border)
            inside &= (p[:, 1] >= border) & (p[:, 1] <= height - 1 - border)
        points = np.concatenate([points, candidates[inside]])[:num_points]
        if len(points) == num_points:
            break
    else:
        raise InvalidValue("baseline", f"found only {len(points)} of {num_points} points seen by both cameras; "
                                       "lower the baseline or raise the distance")
    exact1 = project_points(points, K, None, np.eye(3), np.zeros(3))
    exact2 = project_points(points, K, None, R, t)
    x1 = exact1 + rng.normal(0.0, noise_px, exact1.shape) if noise_px > 0 else exact1.copy()
    x2 = exact2 + rng.normal(0.0, noise_px, exact2.shape) if noise_px > 0 else exact2.copy()
    F = fundamental_from_pose(K, K, R, t) if baseline > 0 else np.zeros((3, 3))
    outliers = np.zeros(num_points, dtype=bool)
    outliers[rng.choice(num_points, int(round(outlier_rate * num_points)), replace=False)] = True
    wrong = np.flatnonzero(outliers)
    while len(wrong):
        x2[wrong] = rng.uniform([border, border], [width - 1 - border, height - 1 - border], (len(wrong), 2))
        far = (np.linalg.norm(x2[wrong] - exact2[wrong], axis=1) > 10.0)
        if baseline > 0:
            far &= _line_distance(F, exact1[wrong], x2[wrong]) > 10.0
        wrong = wrong[~far]
    colors = _point_colors(num_points, rng)
    base = rng.random((num_points, DESCRIPTOR_SIZE))
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    descriptors = np.concatenate([base, base + rng.normal(0.0, 0.01, base.shape)]).astype(np.float32)
    index = np.arange(num_points)
    keypoints = Points2D(np.concatenate([x1, x2]), view=np.repeat([0, 1], num_points),
                         colors=np.concatenate([colors, colors]), image="images")
    track = np.concatenate([index, np.where(outliers, -1, index)])
    images = ImageSet((_dot_image(x1, colors, width, height, "view 0"),
                       _dot_image(x2, colors, width, height, "view 1")))
    direction = t / baseline if baseline > 0 else np.zeros(3)
    state = {"images": images, "K1": K, "K2": K.copy(), "keypoints": keypoints, "descriptors": descriptors,
             "matches": np.column_stack([index, num_points + index]), "x1": x1, "x2": x2}
    truth = {"K1": K, "K2": K.copy(), "R": R, "t": t, "F": F, "E": skew(direction) @ R, "points3d": points,
             "x1_exact": exact1, "x2_exact": exact2, "outliers": outliers, "keypoint_track": track}
    description = (f"Synthetic correspondences: {num_points} points ({structure}) at {distance:g} +- "
                   f"{depth_range / 2:g}, baseline {baseline:g}, noise {noise_px:g} px, "
                   f"{int(outliers.sum())} outliers ({outlier_rate:.0%}), {width}x{height} px, fx={fx:g}")
    return Loaded(state, truth, description)


def _point_colors(count: int, rng: np.random.Generator) -> np.ndarray:
    """Saturated random colours ``(count, 3)`` in [0, 1] (random hues, through OpenCV's HSV)."""
    import cv2

    hsv = np.stack([rng.uniform(0, 360, count), rng.uniform(0.6, 1.0, count), rng.uniform(0.75, 1.0, count)],
                   axis=-1).astype(np.float32)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0].astype(np.float64)


# ----------------------------------------------------------------------------------------------------
# Rendered scenes
# ----------------------------------------------------------------------------------------------------
def _exact_correspondences(depth1: np.ndarray, depth2: np.ndarray, K1: np.ndarray, K2: np.ndarray, R: np.ndarray,
                           t: np.ndarray, *, step: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free pairs from the depth maps: a grid of pixels of image 1 (every ``step`` px) seen in image 2.

    Each pixel centre with a surface is lifted to 3D by its depth, moved by ``(R, t)`` and projected
    into image 2; it is kept when it lands inside image 2 and is not hidden there (the depth of
    image 2 at the nearest pixel agrees within 1 %). Returns ``x1``, ``x2`` ``(N, 2)``.
    """
    height, width = depth1.shape
    u, v = np.meshgrid(np.arange(step // 2, width, step), np.arange(step // 2, height, step))
    x1 = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    z = depth1[v.ravel(), u.ravel()]
    keep = np.isfinite(z) & (z > 0)
    x1, z = x1[keep], z[keep]
    points = np.column_stack([x1, np.ones(len(x1))]) @ np.linalg.inv(K1).T * z[:, None]
    camera2 = points @ R.T + t
    x2 = project_points(points, K2, None, R, t)
    inside = (camera2[:, 2] > 0) & np.all(np.isfinite(x2), axis=1)
    inside &= (x2[:, 0] >= 0) & (x2[:, 0] <= width - 1) & (x2[:, 1] >= 0) & (x2[:, 1] <= height - 1)
    x1, x2, camera2 = x1[inside], x2[inside], camera2[inside]
    seen = depth2[np.round(x2[:, 1]).astype(int), np.round(x2[:, 0]).astype(int)]
    visible = np.abs(seen - camera2[:, 2]) <= 0.01 * camera2[:, 2]
    return x1[visible], x2[visible]


def rendered(*, scene: Literal["room", "table", "facade"] = "room",
             baseline: Annotated[float, Range(0.0, 5.0)] = 0.5,
             noise: Annotated[float, Range(0.0, 0.2)] = 0.005,
             width: Annotated[int, Range(64, 2048)] = 640, height: Annotated[int, Range(48, 2048)] = 480,
             fov_deg: Annotated[float, Range(20.0, 120.0)] = 60.0,
             aim_jitter: Annotated[float, Range(0.0, 0.5)] = 0.05,
             supersample: Annotated[int, Range(1, 4)] = 2, seed: Annotated[int, Range(0, None)] = 0) -> Loaded:
    """Two photographs of a textured 3D scene (:mod:`lab.data.scenes`) from known cameras, with exact depth.

    Camera 1 stands at the scene's ``home`` viewpoint; camera 2 on the circle through it about the
    scene's vertical axis, ``baseline`` metres away (a chord of the orbit). Each looks at the
    scene centre moved by a random offset of ``aim_jitter`` times its distance, so the rotation
    between them is not a pure turn about the vertical. ``baseline = 0`` puts both at one centre (a
    pure rotation: F is not determined). Gaussian pixel noise of ``noise`` (intensities in [0, 1])
    is added to both images. SIFT then finds the features; wrong matches come from the images
    (repeated texture, occlusions): their rate is measured against the depth, not set (the
    ``correspondences`` dataset sets it exactly).

    Args:
        scene: "room" (general depth), "table" (objects in front of a wall) or "facade" (almost a plane).
        baseline: distance between the two camera centres, in metres.
        noise: standard deviation of the pixel noise (intensities in [0, 1]).
        width: image width in pixels.
        height: image height in pixels.
        fov_deg: horizontal field of view in degrees.
        aim_jitter: random offset of each camera's aim, as a fraction of its distance to the centre.
        supersample: anti-aliasing samples per pixel and axis.
        seed: random seed of the scene's textures and layout, the aims and the noise.

    Truth: ``K1``, ``K2``, ``R``, ``t`` (``X_2 = R X_1 + t``, metres), ``F`` (unit norm), ``E``
    (``[t / |t|]_x R``), ``depth`` ``(2, H, W)`` (Z in each camera, ``inf`` on the sky), ``cameras``
    (the two cameras in the scene's world frame), ``x1_exact``, ``x2_exact`` (noise-free
    correspondences sampled from the depth).
    """
    from lab.core import Cameras
    from lab.data.scenes import named_scene, orbit_cameras, render

    check_dataset_pixels(views=2, width=width, height=height, field="width")
    world = named_scene(scene, seed=int(seed))
    centre, up = np.asarray(world.center, dtype=np.float64), np.asarray(world.up, dtype=np.float64)
    offset = np.asarray(world.home, dtype=np.float64) - centre
    radius = float(np.linalg.norm(offset - (offset @ up) * up))
    if baseline > 2 * radius:
        raise InvalidValue("baseline", f"must be at most {2 * radius:.3g} m (the diameter of the orbit around "
                                       f"the {scene!r} scene)")
    arc_deg = float(np.degrees(2 * np.arcsin(baseline / (2 * radius))))
    fx = width / (2.0 * np.tan(np.radians(fov_deg) / 2.0))
    orbit = orbit_cameras(world, num_views=2, arc_deg=arc_deg, fx=fx, width=width, height=height)
    eyes = orbit.centers
    rng = np.random.default_rng([int(seed), 17])
    distances = np.linalg.norm(eyes - centre, axis=1)
    targets = centre + rng.normal(0.0, aim_jitter / np.sqrt(3), (2, 3)) * distances[:, None]
    R_world, t_world = look_at(eyes, targets, up)
    cameras = Cameras(orbit.K, R_world, t_world, width, height, image="images")
    views = [render(world, cameras, i, supersample=int(supersample)) for i in range(2)]
    images = []
    for i, view in enumerate(views):
        pixels = view.image.pixels
        if noise > 0:
            pixels = np.clip(pixels + rng.normal(0.0, noise, pixels.shape).astype(np.float32), 0.0, 1.0)
        images.append(Image(pixels, name=f"{scene} view {i}"))
    K1, K2 = cameras.K[0].copy(), cameras.K[1].copy()
    R = R_world[1] @ R_world[0].T
    t = t_world[1] - R @ t_world[0]
    norm = np.linalg.norm(t)
    if norm < 1e-12 * max(1.0, radius):
        t, norm = np.zeros(3), 0.0
    depth = np.stack([view.depth for view in views])
    x1_exact, x2_exact = _exact_correspondences(depth[0], depth[1], K1, K2, R, t)
    state = {"images": ImageSet(tuple(images)), "K1": K1, "K2": K2}
    truth = {"K1": K1, "K2": K2, "R": R, "t": t, "F": fundamental_from_pose(K1, K2, R, t) if norm else np.zeros((3, 3)),
             "E": skew(t / norm) @ R if norm else np.zeros((3, 3)), "depth": depth, "cameras": cameras,
             "x1_exact": x1_exact, "x2_exact": x2_exact}
    description = (f"Rendered {scene!r} (seed {seed}) from two cameras {baseline:g} m apart, {width}x{height} px, "
                   f"{fov_deg:g} degree field of view, pixel noise {noise:g}")
    return Loaded(state, truth, description)


# ----------------------------------------------------------------------------------------------------
# A user's two photos
# ----------------------------------------------------------------------------------------------------
def read_k_file(file: str) -> tuple[tuple[str, str], np.ndarray]:
    """Two image file names, then the 3 x 3 camera matrix row by row (OpenCV's ``essential_mat_data.txt``).

    Blank lines and lines starting with ``#`` are skipped. Returns the names and ``K``.
    """
    try:
        with open(file, encoding="utf-8") as handle:
            lines = [line.strip() for line in handle if line.strip() and not line.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidValue("k_file", f"cannot read {file!r}: {exc}") from None
    if len(lines) < 5:
        raise InvalidValue("k_file", f"{os.path.basename(file)!r} must hold two image names and three rows of K, "
                                     f"got {len(lines)} lines")
    try:
        K = np.array([[float(v) for v in line.replace(",", " ").split()] for line in lines[2:5]])
    except ValueError:
        raise InvalidValue("k_file", f"{os.path.basename(file)!r}: the rows of K must be numbers") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or not np.allclose(K[2], [0, 0, 1]) or K[0, 0] <= 0 \
            or K[1, 1] <= 0:
        raise InvalidValue("k_file", f"{os.path.basename(file)!r}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
                                     "with positive focal lengths")
    return (lines[0], lines[1]), K


def photos(*, path: str, pattern: str = "*", k_file: str = "", fx: Annotated[float, Range(0.0, 1e6)] = 0.0,
           fy: Annotated[float, Range(0.0, 1e6)] = 0.0, cx: float = -1.0, cy: float = -1.0,
           max_side: Annotated[int, Range(0, 16384)] = 0) -> Loaded:
    """A user's two photos of one scene and, optionally, their camera matrix; no truth.

    The photos are the two images in the folder that match ``pattern``, sorted by name, or the two
    that ``k_file`` names. ``K`` (both views) comes from ``k_file`` (a file in the folder holding
    the two image names then K's three rows, the format of OpenCV's ``essential_mat_data.txt``),
    else from ``fx`` (and ``fy``, ``cx``, ``cy``; defaults: ``fy = fx``, principal point at the
    image centre). Without either, two photos of one size share a guessed K (focal length 1.2
    times the longer side, principal point at the centre: E, R and t are then approximate); two
    photos of different sizes get no K, and the steps that need one say so.

    Args:
        path: the folder that holds the photos.
        pattern: shell pattern of the image file names (e.g. ``leuven*.jpg``); it must match exactly
            two images unless ``k_file`` names them.
        k_file: name of a calibration file in the folder ("" for none).
        fx: focal length along x in pixels (0: not given).
        fy: focal length along y in pixels (0: same as fx).
        cx: principal point x in pixels (negative: the image centre).
        cy: principal point y in pixels (negative: the image centre).
        max_side: shrink both photos so their longer side is at most this many pixels (0: keep), K
            scaled with them.
    """
    import cv2

    check_folder(path)
    names: tuple[str, str] | None = None
    K_file = None
    if k_file:
        if os.sep in k_file or (os.altsep and os.altsep in k_file) or k_file in (".", ".."):
            raise InvalidValue("k_file", f"must be a file name inside the folder, got {k_file!r}")
        names, K_file = read_k_file(os.path.join(path, k_file))
        files = [os.path.join(path, os.path.basename(name)) for name in names]
        missing = [os.path.basename(f) for f in files if not os.path.isfile(f)]
        if missing:
            raise InvalidValue("k_file", f"names {missing} which are not in {path!r}")
    else:
        files = list_images(path, pattern)
        if len(files) != 2:
            raise InvalidValue("path", f"folder {path!r} holds {len(files)} images matching {pattern!r}; two are "
                                       "needed (narrow the pattern, or name them in a k_file)")
    images = read_images(files)
    scales = [1.0, 1.0]
    if max_side:
        for i, image in enumerate(images):
            scale = min(1.0, max_side / max(image.width, image.height))
            if scale < 1.0:
                size = (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
                pixels = cv2.resize(image.pixels, size, interpolation=cv2.INTER_AREA)
                images[i] = Image(np.clip(pixels, 0.0, 1.0), name=image.name)
                scales[i] = size[0] / image.width
    sizes = [(im.width, im.height) for im in images]
    state: dict = {"images": ImageSet(tuple(images))}
    if K_file is not None:
        Ks = [K_file, K_file]
        source = f"K from {k_file}"
    elif fx > 0:
        Ks = [intrinsics(fx, fy if fy > 0 else fx, cx if cx >= 0 else (w - 1) / 2, cy if cy >= 0 else (h - 1) / 2)
              for (w, h) in [(im.width / s, im.height / s) for im, s in zip(images, scales)]]
        source = "K from the options"
    elif sizes[0] == sizes[1]:
        w, h = sizes[0]
        guess = intrinsics(1.2 * max(w, h), 1.2 * max(w, h), (w - 1) / 2, (h - 1) / 2)
        Ks, scales = [guess, guess.copy()], [1.0, 1.0]
        source = "K guessed (focal 1.2 x the longer side, principal point at the centre): E, R, t are approximate"
    else:
        Ks = []
        source = (f"no K: the photos differ in size ({sizes[0][0]}x{sizes[0][1]} and {sizes[1][0]}x{sizes[1][1]}), "
                  "so only F can be estimated")
    for name, K, scale in zip(("K1", "K2"), Ks, scales):
        state[name] = _scaled_intrinsics(K, scale)
    description = f"Two photos from {path}: {images[0].name}, {images[1].name}; {source}"
    return Loaded(state, {}, description)


def _scaled_intrinsics(K: np.ndarray, scale: float) -> np.ndarray:
    """K of an image resized by ``scale`` (pixel centres at integer coordinates: ``c' = (c + 0.5) s - 0.5``)."""
    if scale == 1.0:
        return np.array(K, dtype=np.float64)
    out = np.array(K, dtype=np.float64)
    out[:2, :2] *= scale
    out[:2, 2] = (out[:2, 2] + 0.5) * scale - 0.5
    return out


__all__ = ["rendered", "correspondences", "photos", "read_k_file", "intrinsics", "fundamental_from_pose",
           "relative_pose",
           "DESCRIPTOR_SIZE"]
