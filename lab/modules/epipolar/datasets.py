"""The epipolar module's datasets: synthetic correspondences, a rendered pair with exact truth, a user's
photos.

Every dataset seeds ``images`` (an ImageSet of two) and, where known, the camera matrices ``K1``, ``K2``
(3, 3); the synthetic correspondences (:func:`lab.data.two_view.correspondences`, a generator other tests
build scenes with too) also seed the feature and match values, so the pipeline may start at the estimators.
Conventions (DESIGN.md section 3): camera 1 is the world frame (``R1 = I``, ``t1 = 0``); camera 2 sees
``X_2 = R X_1 + t``; ``x2^T F x1 = 0``; ``E = [t]_x R`` and ``F = K2^-T E K1^-1``.

* :func:`correspondences` - random 3D points projected through two known cameras: exact truth,
  controlled noise and outliers, degenerate configurations on demand.
* :func:`rendered` - a textured scene of :mod:`lab.data.scenes` rendered from two cameras with
  exact ``R``, ``t``, ``K`` and depth, for the whole pipeline from SIFT on.
* :func:`photos` - a folder with two photos and, optionally, their camera matrix (a file in the
  format of OpenCV's ``essential_mat_data.txt``, or ``fx, fy, cx, cy``); no truth.
"""

from __future__ import annotations

import os
from typing import Annotated, Any, Literal

import numpy as np

from lab.core import Image, ImageSet, InvalidValue, Loaded, Range
from lab.core.budgets import check_dataset_pixels
from lab.data.files import WORKING_SIDE, check_folder, list_images, read_working_images
from lab.data.two_view import correspondences, intrinsics
from lab.geometry.camera import project_points, scale_intrinsics
from lab.geometry.rotations import look_at, skew
from lab.geometry.two_view import fundamental_from_pose


def _exact_correspondences(depth1: np.ndarray, depth2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                           R: np.ndarray, t: np.ndarray, *, step: int = 8) -> tuple[np.ndarray, np.ndarray]:
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
             supersample: Annotated[int, Range(1, 4)] = 2,
             seed: Annotated[int, Range(0, None)] = 0) -> Loaded:
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
        raise InvalidValue("baseline", f"must be at most {2 * radius:.3g} m (the diameter of the orbit "
                                       f"around the {scene!r} scene)")
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
        t, norm = np.zeros(3), np.float64(0.0)
    depth = np.stack([view.depth for view in views])
    x1_exact, x2_exact = _exact_correspondences(depth[0], depth[1], K1, K2, R, t)
    state = {"images": ImageSet(tuple(images)), "K1": K1, "K2": K2}
    truth = {"K1": K1, "K2": K2, "R": R, "t": t,
             "F": fundamental_from_pose(K1, K2, R, t) if norm else np.zeros((3, 3)),
             "E": skew(t / norm) @ R if norm else np.zeros((3, 3)), "depth": depth, "cameras": cameras,
             "x1_exact": x1_exact, "x2_exact": x2_exact}
    description = (f"Rendered {scene!r} (seed {seed}) from two cameras {baseline:g} m apart, "
                   f"{width}x{height} px, {fov_deg:g} degree field of view, pixel noise {noise:g}")
    return Loaded(state, truth, description)


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
        raise InvalidValue("k_file", f"{os.path.basename(file)!r} must hold two image names and three rows "
                                     f"of K, got {len(lines)} lines")
    try:
        K = np.array([[float(v) for v in line.replace(",", " ").split()] for line in lines[2:5]])
    except ValueError:
        raise InvalidValue("k_file", f"{os.path.basename(file)!r}: the rows of K must be numbers") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or not np.allclose(K[2], [0, 0, 1]) or K[0, 0] <= 0 \
            or K[1, 1] <= 0:
        raise InvalidValue("k_file", f"{os.path.basename(file)!r}: K must be [[fx, s, cx], [0, fy, cy], [0, "
                                     "0, 1]] with positive focal lengths")
    return (lines[0], lines[1]), K


def photos(*, path: str, pattern: str = "*", k_file: str = "", fx: Annotated[float, Range(0.0, 1e6)] = 0.0,
           fy: Annotated[float, Range(0.0, 1e6)] = 0.0, cx: float = -1.0, cy: float = -1.0,
           max_side: Annotated[int, Range(0, 16384)] = WORKING_SIDE) -> Loaded:
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
        max_side: read the photos at a working size whose longer side is at most this many pixels
            (:data:`lab.data.files.WORKING_SIDE`; 0: full resolution), K scaled with them.
    """
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
            raise InvalidValue("path", f"folder {path!r} holds {len(files)} images matching {pattern!r}; two "
                                       "are needed (narrow the pattern, or name them in a k_file)")
    read = read_working_images(files, max_side=int(max_side))
    images, scales = list(read.images), list(read.scales)
    sizes = [(im.width, im.height) for im in images]
    state: dict[str, Any] = {"images": ImageSet(tuple(images))}
    if K_file is not None:
        Ks = [K_file, K_file]
        source = f"K from {k_file}"
    elif fx > 0:
        Ks = [intrinsics(fx, fy if fy > 0 else fx, cx if cx >= 0 else (w - 1) / 2,
                         cy if cy >= 0 else (h - 1) / 2) for (w, h) in read.original_sizes]
        source = "K from the options"
    elif sizes[0] == sizes[1]:
        w, h = sizes[0]
        guess = intrinsics(1.2 * max(w, h), 1.2 * max(w, h), (w - 1) / 2, (h - 1) / 2)
        Ks, scales = [guess, guess.copy()], [1.0, 1.0]
        source = ("K guessed (focal 1.2 x the longer side, principal point at the centre): E, R, t are "
                  "approximate")
    else:
        Ks = []
        source = (f"no K: the photos differ in size ({sizes[0][0]}x{sizes[0][1]} and "
                  f"{sizes[1][0]}x{sizes[1][1]}), so only F can be estimated")
    for name, K, scale in zip(("K1", "K2"), Ks, scales, strict=False):  # no Ks: no K1, K2
        state[name] = scale_intrinsics(K, scale)
    description = f"Two photos from {path}: {images[0].name}, {images[1].name}; {source}"
    if read.note:
        description += f"; {read.note}"
    return Loaded(state, {}, description)


__all__ = ["correspondences", "photos", "read_k_file", "rendered"]
