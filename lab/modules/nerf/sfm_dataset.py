"""The chain photos -> SfM -> NeRF (issue 17 item 4d): an SfM reconstruction, as the SfM module exports it
(``vision-lab export sfm --format colmap``: a COLMAP text model), read as a NeRF dataset.

The training views are the reconstruction's registered images with their recovered cameras (the SfM
frame: its origin, orientation and unit are the reconstruction's own). The scene's bounds come from the
sparse points, robustly (:func:`bounds_from_points`: a percentile box, so a few stray points do not blow
it up). Held-out views are either

* a **reference** folder in the NeRF-synthetic layout that holds the true cameras of the same training
  images (``transforms_train.json``, frames matched to the model's images by file name) and held-out
  views (``transforms_test.json`` with their images): the true held-out cameras are brought into the SfM
  frame by the similarity that takes the recovered training cameras onto the true ones (Umeyama 1991 on
  the camera centres, :func:`lab.geometry.alignment.align_cameras`), as evaluation tools do (nerfstudio's
  and COLMAP's ``model_aligner``); or, without one,
* every ``test_every``-th registered image (the LLFF / mip-NeRF convention: 0, 8, 16, ...), with its SfM
  pose, left out of training.

State: ``images``, ``cameras`` (OpenCV convention, carrying ``images``), ``test_cameras``, ``bounds`` and
``sfm_points`` (the reconstruction's points as a :class:`PointCloud`, for splatting's
``initialize_gaussians``); truth: ``test_images`` ``(V, H, W, 3)`` and, with a reference, ``alignment``
(the :class:`~lab.geometry.alignment.Similarity` from the SfM frame to the reference's) and
``train_center_error`` (the training camera centres' RMS distance from the truth after alignment, in
the reference's units).
"""

from __future__ import annotations

import os
from typing import Annotated

import cv2
import numpy as np

from lab.core import Cameras, Image, ImageSet, InvalidValue, Loaded, PointCloud, Range
from lab.data.colmap import read_colmap_text
from lab.data.files import check_folder, read_image_file
from lab.data.reconstruction import SparseModel
from lab.geometry.alignment import (Similarity, align_cameras, apply_similarity, camera_centers,
                                    similarity_of_cameras)
from lab.geometry.camera import scale_intrinsics
from lab.modules.nerf.datasets import _carrying, _composited, _read_frames, _read_split, _split_file
from lab.modules.nerf.values import SceneBounds


def bounds_from_points(points: np.ndarray, R: np.ndarray, t: np.ndarray, *, percentile: float = 2.0,
                       margin: float = 1.1) -> SceneBounds:
    """Scene bounds from a sparse reconstruction: the box between the ``percentile`` and
    ``100 - percentile`` percentiles of ``points`` ``(P, 3)`` on each axis, its centre the ``center`` and
    ``margin`` times its half diagonal the ``radius``; ``near`` and ``far`` the least and largest camera
    depth of that centre (cameras ``R`` ``(V, 3, 3)``, ``t`` ``(V, 3)``) minus and plus the radius
    (``near`` at least 1 % of the least depth). Raises :class:`InvalidValue` (field ``points``) with fewer
    than 4 finite points or the centre behind a camera."""
    points = np.asarray(points, dtype=np.float64)
    points = points[np.all(np.isfinite(points), axis=1)] if points.ndim == 2 else points
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise InvalidValue("points", f"expected at least 4 finite 3D points to bound the scene, got "
                                     f"{points.shape}")
    lower, upper = np.percentile(points, [percentile, 100.0 - percentile], axis=0)
    center = 0.5 * (lower + upper)
    radius = margin * 0.5 * float(np.linalg.norm(upper - lower))
    depth = (np.einsum("nij,j->ni", R, center) + t)[:, 2]
    if not np.all(depth > 0):
        raise InvalidValue("points", "the points' centre lies behind a camera: a NeRF dataset needs cameras "
                                     "looking at the scene")
    near = max(float(depth.min()) - radius, 0.01 * float(depth.min()))
    return SceneBounds(near, float(depth.max()) + radius, center, radius)


def _image_folder(path: str, images: str) -> str:
    if images:
        return check_folder(images)
    beside = os.path.join(os.path.dirname(path.rstrip("/")), "images")
    for candidate in (os.path.join(path, "images"), beside):
        if os.path.isdir(candidate):
            return candidate
    raise InvalidValue("images", f"no images folder beside {path!r} (looked for images/ in it and beside "
                                 "it): name the folder holding the model's images")


def _read_views(model: SparseModel, folder: str, downscale: int) -> list[np.ndarray]:
    """The model's images from ``folder``, composited on white, shrunk ``downscale`` times."""
    out = []
    for name, (width, height) in zip(model.names, model.sizes, strict=True):
        file = os.path.join(folder, name)
        if not os.path.isfile(file):
            raise InvalidValue("images", f"the model's image {name!r} is not in {folder!r}")
        pixels = _composited(read_image_file(file), name)
        if (pixels.shape[1], pixels.shape[0]) != (int(width), int(height)):
            raise InvalidValue("images", f"{name} is {pixels.shape[1]}x{pixels.shape[0]} but the model says "
                                         f"{width}x{height}")
        if width % downscale or height % downscale:
            raise InvalidValue("downscale", f"{width}x{height} images do not divide by {downscale}")
        if downscale > 1:
            pixels = cv2.resize(pixels, (int(width) // downscale, int(height) // downscale),
                                interpolation=cv2.INTER_AREA)
        out.append(pixels)
    if len({im.shape for im in out}) != 1:
        raise InvalidValue("images", "every view must have one size")
    return out


def _stem(name: str) -> str:
    return os.path.splitext(os.path.basename(name))[0]


def _reference_test(reference: str, model: SparseModel, limit: int,
                    downscale: int) -> tuple[Cameras, list[np.ndarray], Similarity, float]:
    """The reference's held-out cameras in the SfM frame, their images, the alignment and the training
    centres' RMS error after it (module docstring)."""
    folder = check_folder(reference)
    _, _, R_true, t_true, names = _read_frames(_split_file(folder, "train"), folder)
    index = {_stem(name): i for i, name in enumerate(names)}
    missing = [name for name in model.names if _stem(name) not in index]
    if missing:
        raise InvalidValue("reference", f"transforms_train.json of {folder!r} has no frame for the model's "
                                        f"images {missing[:5]}")
    pick = np.array([index[_stem(name)] for name in model.names])
    R_sfm, t_sfm = model.poses[:, :, :3], model.poses[:, :, 3]
    to_true = align_cameras(R_sfm, t_sfm, R_true[pick], t_true[pick])
    error = apply_similarity(to_true, camera_centers(R_sfm, t_sfm)) \
        - camera_centers(R_true[pick], t_true[pick])
    test_images, test = _read_split(folder, "test", limit, downscale)
    R, t = similarity_of_cameras(to_true.inverse(), test.R, test.t)
    cameras = Cameras(test.K, R, t, test.width, test.height)
    return cameras, test_images, to_true, float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


def sfm_reconstruction(*, path: str, images: str = "", reference: str = "",
                       downscale: Annotated[int, Range(1, 16)] = 1,
                       test_every: Annotated[int, Range(2, 100)] = 8,
                       test_views: Annotated[int, Range(1, 400)] = 25,
                       percentile: Annotated[float, Range(0.0, 25.0)] = 2.0,
                       margin: Annotated[float, Range(1.0, 3.0)] = 1.1) -> Loaded:
    """An SfM reconstruction (a COLMAP text model, as ``vision-lab export sfm --format colmap`` writes it)
    with its images, as a NeRF dataset in the reconstruction's frame (the module docstring).

    Args:
        path: the folder holding cameras.txt, images.txt and points3D.txt.
        images: the folder holding the model's images (default: images/ in ``path`` or beside it).
        reference: a NeRF-synthetic-layout folder with the true cameras of the training images and the
            held-out views (default: none; every ``test_every``-th image is held out).
        downscale: integer factor the images are shrunk by (area averaging; the state's
            ``pixel_supersample``, as :func:`~lab.modules.nerf.nerf_synthetic` gives it).
        test_every: without a reference, hold out images 0, test_every, 2 test_every, ...
        test_views: with a reference, at most this many held-out views (its first ones).
        percentile: the points' box spans this to 100 - this percentile on each axis.
        margin: the bounding radius is this many times the box's half diagonal.
    """
    model = read_colmap_text(check_folder(path)).compact()
    if len(model.names) < 2:
        raise InvalidValue("path", f"the model at {path!r} has {len(model.names)} registered image; NeRF "
                                   "needs at least 2")
    pixels = _read_views(model, _image_folder(path, images), int(downscale))
    K = np.stack([scale_intrinsics(k, 1.0 / int(downscale)) for k in model.K])
    height, width = pixels[0].shape[:2]
    R, t = model.poses[:, :, :3], model.poses[:, :, 3]
    truth: dict[str, object] = {}
    if reference:
        train = np.arange(len(pixels))
        test, test_images, to_true, error = _reference_test(reference, model, int(test_views), int(downscale))
        if (test.width, test.height) != (width, height):
            raise InvalidValue("reference", f"held-out views are {test.width}x{test.height}, the model's "
                                            f"images {width}x{height} at downscale {downscale}")
        truth.update(alignment=to_true, train_center_error=error)
    else:
        held = np.arange(len(pixels)) % int(test_every) == 0
        if held.all() or not held.any():
            raise InvalidValue("test_every", f"holding out every {test_every}th of {len(pixels)} images "
                                             "leaves nothing to train on or to evaluate")
        train = np.flatnonzero(~held)
        test = Cameras(K[held], R[held], t[held], width, height)
        test_images = [pixels[i] for i in np.flatnonzero(held)]
    bounds = bounds_from_points(model.points, R[train], t[train], percentile=percentile, margin=margin)
    cameras = Cameras(K[train], R[train], t[train], width, height)
    state = {"images": ImageSet(tuple(Image(pixels[i], name=model.names[i]) for i in train)),
             "cameras": _carrying(cameras, "images"), "test_cameras": test, "bounds": bounds,
             "sfm_points": PointCloud(model.points, model.colors.astype(np.float64) / 255.0),
             # each pixel is the area mean of downscale x downscale photo pixels: held-out renders follow it
             "pixel_supersample": int(downscale)}
    truth["test_images"] = np.stack(test_images)
    held_from = (f"the reference {reference!r} aligned by Umeyama" if reference
                 else f"every {test_every}th image")
    return Loaded(state, truth, f"an SfM reconstruction from {path!r}: {len(train)} training views with "
                                f"their recovered cameras, {len(test_images)} held out ({held_from}), "
                                f"{width}x{height}, {len(model.points)} points bound the scene")


__all__ = ["bounds_from_points", "sfm_reconstruction"]
