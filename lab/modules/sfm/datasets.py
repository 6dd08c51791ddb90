"""The SfM module's datasets: rendered scenes with exact truth, a folder of photos, the course's match files.

Every dataset seeds the state the SfM steps read (:mod:`lab.modules.sfm.steps`): ``images`` (an
ImageSet of ``V >= 2`` views) and ``K`` ``(V, 3, 3)`` (one camera matrix per view; OpenCV pixel
convention, pixel (0, 0) the centre of the top-left pixel). Ground truth is returned apart from the
state (DESIGN.md section 1) so no step can see it.

* :func:`rendered` - a textured scene of :mod:`lab.data.scenes` rendered along an orbit or a
  forward path, with exact poses, ``K`` and depth. Nothing is cached on disk; only the views asked
  for are rendered.
* :func:`photos` - a user's folder of photos with ``K`` from a file, from ``fx, fy, cx, cy``, or
  guessed from the EXIF focal length (35 mm equivalent; Pillow reads it) or, failing that, from the
  image size. A guess is said so in the description.
* :func:`match_files` - the classic course format (``matching1.txt`` ...) read by
  :func:`lab.data.matchfile.read_match_files`: its keypoints and pairwise matches replace SIFT and
  matching, so the pipeline starts at geometric verification.
"""

from __future__ import annotations

import os
from typing import Annotated, Literal

import numpy as np

from lab.core import Image, ImageSet, InvalidValue, Loaded, Points2D, Range
from lab.core.budgets import check_dataset_pixels
from lab.data.files import WORKING_SIDE, check_folder, list_images, read_working_images
from lab.data.matchfile import MatchFiles, read_match_files
from lab.geometry.camera import scale_intrinsics

#: 35 mm film diagonal, millimetres (EXIF ``FocalLengthIn35mmFilm`` is relative to it).
FILM_DIAGONAL_MM = float(np.hypot(36.0, 24.0))

#: Focal length guessed without K or EXIF, as a multiple of the longer image side.
FOCAL_GUESS_FACTOR = 1.2


def check_intrinsics(K: np.ndarray, images: ImageSet, *, name: str = "K") -> np.ndarray:
    """``K`` as ``(V, 3, 3)`` float64, checked against the images; :class:`InvalidValue` names the misfit.

    A ``(3, 3)`` matrix is shared by all views. Each K must be ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``
    with positive focal lengths and its principal point inside its image (a K calibrated at another
    resolution has it outside, or far off the centre: more than 25 % of the side away).
    """
    if not isinstance(images, ImageSet) or len(images) == 0:
        raise InvalidValue("images", "expected an ImageSet")
    K = np.asarray(K, dtype=np.float64)
    if K.shape == (3, 3):
        K = np.broadcast_to(K, (len(images), 3, 3)).copy()
    if K.shape != (len(images), 3, 3):
        raise InvalidValue(name,
                           f"expected one camera matrix per image, ({len(images)}, 3, 3), got {K.shape}")
    if not np.all(np.isfinite(K)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    for i, (k, image) in enumerate(zip(K, images.images, strict=True)):
        label = f"K of image {i} ({images.names[i]})"
        if not np.allclose(k[2], (0.0, 0.0, 1.0)) or k[1, 0] != 0 or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise InvalidValue(name,
                               f"{label} must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with positive focal "
                               f"lengths")
        w, h = image.width, image.height
        cx, cy = k[0, 2], k[1, 2]
        if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5) or abs(cx - (w - 1) / 2) > 0.25 * w \
                or abs(cy - (h - 1) / 2) > 0.25 * h:
            raise InvalidValue(name,
                               f"{label} does not fit the {w}x{h} image: its principal point ({cx:.1f}, "
                               f"{cy:.1f}) is far from the image centre ({(w - 1) / 2:.1f}, "
                               f"{(h - 1) / 2:.1f}) (was it calibrated at another resolution?)")
    return K


# ----------------------------------------------------------------------------------------------------
# Rendered scenes
# ----------------------------------------------------------------------------------------------------
def camera_path(scene: str = "room", path: str = "orbit", *, num_views: int = 12, arc_deg: float = 120.0,
                step: float = 0.2, turn_deg: float = 1.0, width: int = 640, height: int = 480,
                fov_deg: float = 60.0, seed: int = 0):
    """The scene and the true cameras of :func:`rendered` (no rendering): ``(Scene, Cameras)``."""
    from lab.data.scenes import forward_cameras, named_scene, orbit_cameras

    world = named_scene(scene, seed=int(seed))
    fx = width / (2.0 * np.tan(np.radians(fov_deg) / 2.0))
    if path == "orbit":
        cameras = orbit_cameras(world, num_views=int(num_views), arc_deg=float(arc_deg), fx=fx, width=width,
                                height=height)
    elif path == "forward":
        cameras = forward_cameras(num_views=int(num_views), step=float(step), scene=world,
                                  turn_deg=float(turn_deg), fx=fx, width=width, height=height)
    else:
        raise InvalidValue("path", f"must be 'orbit' or 'forward', got {path!r}")
    return world, cameras


def scene_extent(centers: np.ndarray) -> float:
    """Size of a camera path: the largest distance between two camera centres ``(V, 3)`` (metres)."""
    centers = np.asarray(centers, dtype=np.float64)
    if len(centers) < 2:
        return 0.0
    return float(np.max(np.linalg.norm(centers[:, None] - centers[None], axis=2)))


def rendered(*, scene: Literal["room", "table", "facade"] = "room",
             path: Literal["orbit", "forward"] = "orbit", num_views: Annotated[int, Range(2, 30)] = 12,
             arc_deg: Annotated[float, Range(5.0, 360.0)] = 120.0,
             step: Annotated[float, Range(0.01, 2.0)] = 0.2,
             turn_deg: Annotated[float, Range(-10.0, 10.0)] = 1.0,
             width: Annotated[int, Range(64, 2048)] = 640, height: Annotated[int, Range(48, 2048)] = 480,
             fov_deg: Annotated[float, Range(20.0, 120.0)] = 60.0,
             noise: Annotated[float, Range(0.0, 0.2)] = 0.005,
             supersample: Annotated[int, Range(1, 4)] = 2,
             seed: Annotated[int, Range(0, None)] = 0) -> Loaded:
    """Photographs of a textured 3D scene (:mod:`lab.data.scenes`) from known cameras on a path, exact depth.

    "orbit": views on an arc of ``arc_deg`` degrees about the scene's vertical axis through its
    centre, starting at its ``home`` viewpoint, all looking at the centre
    (:func:`lab.data.scenes.orbit_cameras`). "forward": views ``step`` metres apart walking from
    ``home`` towards the centre, turning ``turn_deg`` degrees per view
    (:func:`lab.data.scenes.forward_cameras`). Gaussian pixel noise of ``noise`` is added.

    Args:
        scene: "room" (general depth), "table" (objects before a wall) or "facade" (almost a plane).
        path: "orbit" or "forward".
        num_views: number of photographs.
        arc_deg: the orbit's arc in degrees (360: a full turn).
        step: distance between views on the forward path, metres.
        turn_deg: turn per view on the forward path, degrees.
        width: image width in pixels.
        height: image height in pixels.
        fov_deg: horizontal field of view in degrees.
        noise: standard deviation of the pixel noise (intensities in [0, 1]).
        supersample: anti-aliasing samples per pixel and axis.
        seed: random seed of the scene's textures and layout and the noise.

    State: ``images``, ``K`` ``(V, 3, 3)``. Truth: ``cameras`` (Cameras, world frame of the scene),
    ``R`` ``(V, 3, 3)``, ``t`` ``(V, 3)``, ``K``, ``depth`` ``(V, H, W)`` (Z in each camera,
    ``inf`` on the sky) and ``scene_size`` (the largest distance between two true camera centres,
    the unit of the relative centre error).
    """
    from lab.core import Cameras
    from lab.data.scenes import render

    check_dataset_pixels(views=num_views, width=width, height=height)
    world, cameras = camera_path(scene, path, num_views=num_views, arc_deg=arc_deg, step=step,
                                 turn_deg=turn_deg,
                                 width=int(width), height=int(height), fov_deg=fov_deg, seed=seed)
    rng = np.random.default_rng([int(seed), 23])
    images, depth = [], []
    for i in range(len(cameras)):
        view = render(world, cameras, i, supersample=int(supersample))
        pixels = view.image.pixels
        if noise > 0:
            pixels = np.clip(pixels + rng.normal(0.0, noise, pixels.shape).astype(np.float32), 0.0, 1.0)
        images.append(Image(pixels, name=f"{scene}_{i:02d}.png"))
        depth.append(view.depth)
    K = cameras.K.copy()
    true_cameras = Cameras(K, cameras.R, cameras.t, cameras.width, cameras.height, image="images")
    truth = {"cameras": true_cameras, "R": cameras.R.copy(), "t": cameras.t.copy(), "K": K.copy(),
             "depth": np.stack(depth), "scene_size": scene_extent(cameras.centers)}
    description = (f"Rendered {scene!r} (seed {seed}) from {len(cameras)} cameras on a {path} path, "
                   f"{width}x{height} px, {fov_deg:g} degree field of view, pixel noise {noise:g}; exact K, "
                   "poses and depth")
    return Loaded({"images": ImageSet(tuple(images)), "K": K}, truth, description)


# ----------------------------------------------------------------------------------------------------
# A user's photos
# ----------------------------------------------------------------------------------------------------
def read_k_matrix(file: str) -> np.ndarray:
    """The ``3 x 3`` camera matrix of a text file: its last three rows of three numbers.

    Reads OpenCV's ``essential_mat_data.txt`` layout (image names, then K) and a bare K alike;
    blank lines and ``#`` comments are skipped, commas count as spaces.
    """
    try:
        with open(file, encoding="utf-8") as handle:
            lines = [line.strip() for line in handle if line.strip() and not line.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidValue("k_file", f"cannot read {os.path.basename(file)!r}: {exc}") from None
    rows = []
    for line in lines:
        try:
            values = [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            continue
        if len(values) == 3:
            rows.append(values)
    if len(rows) < 3:
        raise InvalidValue("k_file",
                           f"{os.path.basename(file)!r} must hold the three rows of K (three numbers each), "
                           f"found {len(rows)}")
    return np.array(rows[-3:], dtype=np.float64)


def exif_focal_px(file: str, width: int, height: int) -> float | None:
    """Focal length in pixels from a photo's EXIF ``FocalLengthIn35mmFilm`` (Pillow), None when absent.

    ``f_px = f_35 * diagonal_px / 43.27`` (the 35 mm film diagonal in mm): the 35 mm equivalent is
    defined on the diagonal, so it holds for any aspect ratio.
    """
    try:
        from PIL import Image as PILImage

        with PILImage.open(file) as photo:
            exif = photo.getexif()
            sub = exif.get_ifd(0x8769) if hasattr(exif, "get_ifd") else {}
            f35 = sub.get(41989) or exif.get(41989)
    except Exception:  # not an image Pillow reads, no EXIF: no guess from it
        return None
    if f35 is None:
        return None
    try:
        f35 = float(f35)
    except (TypeError, ValueError):
        return None
    if not f35 > 0:
        return None
    return f35 * float(np.hypot(width, height)) / FILM_DIAGONAL_MM


def _intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def photos(*, path: str, pattern: str = "*", k_file: str = "", fx: Annotated[float, Range(0.0, 1e6)] = 0.0,
           fy: Annotated[float, Range(0.0, 1e6)] = 0.0, cx: float = -1.0, cy: float = -1.0,
           max_side: Annotated[int, Range(0, 16384)] = WORKING_SIDE) -> Loaded:
    """A user's photos of one scene (at least two) and their camera matrix; no truth.

    ``K`` comes from ``k_file`` (a file in the folder whose last three rows of numbers are K, e.g.
    OpenCV's ``essential_mat_data.txt``), else from ``fx`` (and ``fy``, ``cx``, ``cy``: defaults
    ``fy = fx`` and the image centre), both for the photos' original size; else it is **guessed** per
    photo: the focal length from the EXIF 35 mm equivalent when the photo has one, otherwise
    1.2 times the longer side, with the principal point at the centre. The description says which.

    Args:
        path: the folder that holds the photos.
        pattern: shell pattern of the image file names (e.g. ``*.jpg``).
        k_file: name of a calibration file in the folder ("" for none).
        fx: focal length along x in pixels (0: not given).
        fy: focal length along y in pixels (0: same as fx).
        cx: principal point x in pixels (negative: the image centre).
        cy: principal point y in pixels (negative: the image centre).
        max_side: read the photos at a working size whose longer side is at most this many pixels
            (:data:`lab.data.files.WORKING_SIDE`; 0: full resolution), K scaled with them.
    """
    check_folder(path)
    files = list_images(path, pattern)
    if len(files) < 2:
        raise InvalidValue("path",
                           f"folder {path!r} holds {len(files)} images matching {pattern!r}; structure from "
                           "motion needs at least two")
    read = read_working_images(files, max_side=int(max_side))
    images, scales = list(read.images), read.scales
    Ks = []
    if k_file:
        if os.sep in k_file or (os.altsep and os.altsep in k_file) or k_file in (".", ".."):
            raise InvalidValue("k_file", f"must be a file name inside the folder, got {k_file!r}")
        K = read_k_matrix(os.path.join(path, k_file))
        Ks = [scale_intrinsics(K, s) for s in scales]
        source = f"K from {k_file}"
    elif fx > 0:
        for (width, height), s in zip(read.original_sizes, scales, strict=True):
            K = _intrinsics(fx, fy if fy > 0 else fx, cx if cx >= 0 else (width - 1) / 2,
                            cy if cy >= 0 else (height - 1) / 2)
            Ks.append(scale_intrinsics(K, s))
        source = "K from the options"
    else:
        from_exif = 0
        for file, image in zip(files, images, strict=True):
            focal = exif_focal_px(file, image.width, image.height)
            from_exif += focal is not None
            focal = FOCAL_GUESS_FACTOR * max(image.width, image.height) if focal is None else focal
            Ks.append(_intrinsics(focal, focal, (image.width - 1) / 2, (image.height - 1) / 2))
        source = (f"K GUESSED, not calibrated: the focal length from the EXIF 35 mm equivalent for "
                  f"{from_exif} of {len(images)} photos, else {FOCAL_GUESS_FACTOR} x the longer side, "
                  "principal point at the centre (poses and points are approximate; give k_file or fx for a "
                  "calibrated reconstruction)")
    image_set = ImageSet(tuple(images))
    K = check_intrinsics(np.stack(Ks), image_set)
    description = f"{len(images)} photos from {path}; {source}"
    if read.note:
        description += f"; {read.note}"
    return Loaded({"images": image_set, "K": K}, {}, description)


# ----------------------------------------------------------------------------------------------------
# The course's match files
# ----------------------------------------------------------------------------------------------------
def matches_from_match_files(match_files: MatchFiles) -> tuple[Points2D, np.ndarray]:
    """The keypoints and pairwise matches of :class:`lab.data.matchfile.MatchFiles` in the SfM module's form.

    Returns ``keypoints`` (Points2D: every image's keypoints in image order, ``view`` per point,
    colours in [0, 1]) and ``matches`` ``(M, 4)`` int64 rows ``(view a, view b, keypoint a,
    keypoint b)`` with ``a < b`` and global keypoint indices (into ``keypoints``).
    """
    counts = [len(k) for k in match_files.keypoints]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    xy = np.concatenate([np.asarray(k, dtype=np.float64).reshape(-1, 2) for k in match_files.keypoints])
    view = np.repeat(np.arange(len(counts)), counts)
    colors = np.concatenate([np.asarray(c, dtype=np.float64).reshape(-1, 3)
                             for c in match_files.colors]) / 255.0
    rows = [np.column_stack([np.full(len(m), a), np.full(len(m), b), offsets[a] + m[:, 0],
                             offsets[b] + m[:, 1]])
            for (a, b), m in sorted(match_files.matches.items()) if len(m)]
    matches = np.concatenate(rows).astype(np.int64) if rows else np.zeros((0, 4), dtype=np.int64)
    return Points2D(xy, view=view, colors=colors, image="images"), matches


def match_files(*, path: str, pattern: str = "*", k_file: str = "calibration.txt",
                fx: Annotated[float, Range(0.0, 1e6)] = 0.0, fy: Annotated[float, Range(0.0, 1e6)] = 0.0,
                cx: float = -1.0, cy: float = -1.0) -> Loaded:
    """The classic course dataset: photos, ``matching<i>.txt`` match files and a calibration file; no truth.

    The match files (:mod:`lab.data.matchfile`) give every image's keypoints and the matches between
    images, which replace the feature and matching steps: start the pipeline at ``verify_pairs``.
    Images are the folder's image files matching ``pattern``, sorted by name (image ``i`` of the
    match files is the ``i``-th). K as in :func:`photos` (``k_file`` "" and ``fx`` 0: guessed).

    Args:
        path: the folder with the photos and the match files.
        pattern: shell pattern of the image file names.
        k_file: name of the calibration file in the folder ("" for none).
        fx: focal length along x in pixels (0: not given).
        fy: focal length along y in pixels (0: same as fx).
        cx: principal point x in pixels (negative: the image centre).
        cy: principal point y in pixels (negative: the image centre).
    """
    check_folder(path)
    if k_file and not os.path.isfile(os.path.join(path, k_file)):
        k_file = "" if k_file == "calibration.txt" else k_file
    loaded = photos(path=path, pattern=pattern, k_file=k_file, fx=fx, fy=fy, cx=cx, cy=cy)
    images: ImageSet = loaded.state["images"]
    found = read_match_files(path, num_images=len(images))
    keypoints, matches = matches_from_match_files(found)
    state = dict(loaded.state, keypoints=keypoints, matches=matches)
    description = (f"{loaded.description}; {len(keypoints)} keypoints and {len(matches)} matches from "
                   f"{len(found.sources)} match files ({found.inconsistent_tracks} inconsistent tracks "
                   "dropped by the reader); start at verify_pairs")
    return Loaded(state, {}, description)


__all__ = [
    "FOCAL_GUESS_FACTOR", "camera_path", "check_intrinsics", "exif_focal_px", "match_files",
    "matches_from_match_files", "photos", "read_k_matrix", "rendered", "scene_extent",
]
