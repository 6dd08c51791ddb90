"""Stereo pairs with their calibration: Middlebury's motorcycle, synthetic pairs with exact disparity, a
user's folder.

Every loader returns the state ``left_raw``, ``right_raw`` (:class:`lab.core.Image`) and
``calibration`` (:class:`lab.geometry.rectification.StereoCalibration`); a pair that is rectified
already has a calibration with no rotation and no distortion, which the stereo module's
``rectify_pair`` step passes through. Ground truth (``Loaded.truth``), when known:

- ``disparity`` ``(H, W)`` float64 in pixels for the *rectified* left image, -1 where unknown;
- ``depth`` ``(H, W)`` float64, Z in the rectified left camera frame (metres), 0 where unknown;
- ``points`` ``(N, 3)`` points of the scene in the raw left camera frame (synthetic pairs), to
  measure how well rectification aligns rows.

Disparity convention: left pixel ``(x, y)`` is seen at ``(x - d, y)`` in the right image, and
``Z = f B / (d + disparity_offset)`` with ``disparity_offset = cx_right - cx_left``.
"""

from __future__ import annotations

import json
import os
from typing import Annotated, Any, Literal

import numpy as np

from lab.core import Image, InvalidValue, Loaded, Range
from lab.core.budgets import check_dataset_pixels
from lab.data.files import IMAGE_SUFFIXES, WORKING_SIDE, check_folder, read_image_file, read_working_images
from lab.geometry.camera import scale_intrinsics
from lab.geometry.rectification import StereoCalibration, relative_pose, stereo_rectify

#: Calibration of scikit-image's motorcycle pair (its docstring; Middlebury 2014 downsampled 4 times).
MOTORCYCLE_FOCAL_PX = 994.978
MOTORCYCLE_CENTRE_PX = (311.193, 254.877)
MOTORCYCLE_DOFFS_PX = 31.086
MOTORCYCLE_BASELINE_M = 0.193001


# --- scikit-image's Middlebury motorcycle -------------------------------------------------------------------
def _downsample(pixels: np.ndarray, factor: int) -> np.ndarray:
    """Mean over ``factor x factor`` blocks (rows and columns beyond a whole block are dropped)."""
    if factor == 1:
        return pixels
    h, w = (pixels.shape[0] // factor) * factor, (pixels.shape[1] // factor) * factor
    blocks = pixels[:h, :w].reshape(h // factor, factor, w // factor, factor, *pixels.shape[2:])
    return blocks.mean(axis=(1, 3))


def _downsample_disparity(disparity: np.ndarray, factor: int) -> np.ndarray:
    """Block mean of the known disparities, divided by ``factor`` (disparities shrink with the image); -1
    unknown."""
    if factor == 1:
        return disparity
    known = disparity >= 0
    total = _downsample(np.where(known, disparity, 0.0), factor)
    count = _downsample(known.astype(np.float64), factor)
    return np.where(count > 0, total / np.maximum(count, 1e-12) / factor, -1.0)


def _scaled_calibration(calibration: StereoCalibration, scale: float) -> StereoCalibration:
    """The calibration of a pair both of whose images were resized by ``scale`` (R and T unchanged; a
    ``downsample`` by f is ``1 / f``)."""
    if scale == 1.0:
        return calibration
    return StereoCalibration(scale_intrinsics(calibration.K_left, scale), calibration.dist_left,
                             scale_intrinsics(calibration.K_right, scale), calibration.dist_right,
                             calibration.R, calibration.T)


def _scaled_disparity(disparity: np.ndarray, scale: float, size: tuple[int, int]) -> np.ndarray:
    """A true disparity map of the file's size at the working ``size`` ``(width, height)``: nearest
    neighbour (a mean would blend across depth edges), known values times ``scale``; -1 unknown."""
    import cv2

    nearest = cv2.resize(disparity.astype(np.float32), size, interpolation=cv2.INTER_NEAREST)
    return np.where(nearest >= 0, nearest.astype(np.float64) * scale, -1.0)


def _motorcycle_calibration() -> StereoCalibration:
    f = MOTORCYCLE_FOCAL_PX
    K = np.array([[f, 0.0, MOTORCYCLE_CENTRE_PX[0]], [0.0, f, MOTORCYCLE_CENTRE_PX[1]], [0.0, 0.0, 1.0]])
    return StereoCalibration.rectified(K, MOTORCYCLE_BASELINE_M, disparity_offset=MOTORCYCLE_DOFFS_PX)


def motorcycle(*, downsample: Annotated[int, Range(1, 8)] = 1) -> Loaded:
    """The Middlebury 2014 motorcycle pair shipped with scikit-image (741 x 500, rectified), with true
    disparity.

    ``skimage.data.stereo_motorcycle()`` (offline in the wheel): disparities 7 to 60 px, about
    7 % of the pixels without truth. ``downsample`` shrinks both images (block means) and the
    truth by an integer factor. Calibration from scikit-image's docstring: f = 994.978 px,
    principal point (311.193, 254.877), ``doffs`` = 31.086 px, baseline 193.001 mm.

    Args:
        downsample: integer factor by which to shrink the images.

    Reference: D. Scharstein et al., "High-resolution stereo datasets with subpixel-accurate ground
    truth", GCPR 2014.
    """
    from skimage import data

    factor = int(downsample)
    left, right, disparity = data.stereo_motorcycle()
    truth = np.where(np.isfinite(disparity), disparity.astype(np.float64), -1.0)
    left = _downsample(left.astype(np.float32) / 255.0, factor).astype(np.float32)
    right = _downsample(right.astype(np.float32) / 255.0, factor).astype(np.float32)
    truth = _downsample_disparity(truth, factor)
    calibration = _scaled_calibration(_motorcycle_calibration(), 1.0 / factor)
    depth = np.where(truth >= 0, calibration.K_left[0, 0] * calibration.baseline
                     / np.maximum(truth + MOTORCYCLE_DOFFS_PX / factor, 1e-9), 0.0)
    return Loaded(state={"left_raw": Image(left, name="motorcycle left"),
                         "right_raw": Image(right, name="motorcycle right"), "calibration": calibration},
                  truth={"disparity": truth, "depth": depth},
                  description=f"Middlebury 2014 motorcycle (scikit-image), {left.shape[1]} x "
                              f"{left.shape[0]}, rectified, with true disparity")


# --- synthetic pairs rendered with exact disparity ------------------------------------------------------
def synthetic(*, scene: Literal["table", "room", "facade"] = "table", rectified: bool = True,
              width: Annotated[int, Range(32, 1920)] = 640, height: Annotated[int, Range(32, 1080)] = 480,
              baseline: Annotated[float, Range(0.01, 2.0)] = 0.12,
              verge_deg: Annotated[float, Range(0.0, 20.0)] = 4.0,
              k1: Annotated[float, Range(-0.3, 0.3)] = -0.05, noise: Annotated[float, Range(0.0, 0.2)] = 0.0,
              seed: Annotated[int, Range(0, None)] = 0) -> Loaded:
    """A pair rendered from a named scene by the shared ray caster, with exact disparity and depth.

    The left camera sits at the scene's home viewpoint; the right one ``baseline`` metres along
    its x axis (:func:`lab.data.scenes.stereo_rig`). Rectified (``rectified=True``): both share
    orientation and intrinsics, so ``d = f B / Z`` exactly. Unrectified: the cameras toe in by
    ``verge_deg`` (half each) and their lenses have radial distortion ``k1``; the truth then
    describes the pair as :func:`lab.geometry.rectification.stereo_rectify` rectifies it (the
    scene is rendered once more through the rectified left camera for its depth). Images get
    Gaussian noise of standard deviation ``noise``; ``seed`` varies the scene.

    Args:
        scene: which named scene (lab.data.scenes).
        rectified: render a rectified pair, or a verged pair with distortion.
        width: image width in pixels.
        height: image height in pixels.
        baseline: distance between the cameras (metres).
        verge_deg: toe-in of the unrectified pair (degrees).
        k1: radial distortion of the unrectified pair.
        noise: standard deviation of the pixel noise.
        seed: varies the scene's textures and layout, and the noise.
    """
    from lab.data.scenes import named_scene, render, stereo_rig
    from lab.geometry.camera import as_distortion
    from lab.core import Cameras

    check_dataset_pixels(views=2, width=width, height=height, field="width")
    world = named_scene(scene, seed=int(seed))
    dist = None if rectified else np.array([k1, 0.0, 0.0, 0.0, 0.0])
    rig = stereo_rig(baseline=float(baseline), scene=world, width=int(width), height=int(height),
                     verge_deg=0.0 if rectified else float(verge_deg), dist=dist)
    views = [render(world, rig, index, supersample=2) for index in (0, 1)]
    rng = np.random.default_rng([int(seed), 7])
    images = []
    for view, side in zip(views, ("left", "right"), strict=True):
        pixels = view.image.pixels
        if noise > 0:
            noisy = pixels + rng.normal(0.0, float(noise), pixels.shape)
            pixels = np.clip(noisy, 0.0, 1.0).astype(np.float32)
        images.append(Image(pixels, name=f"{scene} {side}"))
    R, T = relative_pose(rig.R[0], rig.t[0], rig.R[1], rig.t[1])
    d = as_distortion(dist)
    calibration = StereoCalibration(rig.K[0], d, rig.K[1], d, R, T)
    if rectified:
        depth = np.where(views[0].mask, views[0].depth, 0.0)
        focal = rig.K[0][0, 0]
        rows, columns = np.nonzero(depth > 0)
    else:
        rect = stereo_rectify(rig.K[0], d, rig.K[1], d, (int(width), int(height)), R, T)
        rectified_left = Cameras(rect.K, rect.R_left @ rig.R[0], rect.R_left @ rig.t[0], int(width),
                                 int(height))
        view = render(world, rectified_left, 0, supersample=1)
        depth = np.where(view.mask, view.depth, 0.0)
        focal = rect.K[0, 0]
        rows, columns = np.nonzero(depth > 0)
    disparity = np.where(depth > 0, focal * calibration.baseline / np.where(depth > 0, depth, 1.0), -1.0)
    truth: dict[str, Any] = {"disparity": disparity, "depth": depth}
    if not rectified and len(rows):
        pick = rng.choice(len(rows), size=min(500, len(rows)), replace=False)
        pixels = np.stack([columns[pick], rows[pick], np.ones(len(pick))], axis=1)
        in_rectified = (pixels @ np.linalg.inv(rect.K).T) * depth[rows[pick], columns[pick]][:, None]
        truth["points"] = in_rectified @ rect.R_left  # rectified frame -> raw left camera frame
    kind = "rectified" if rectified else f"verged {verge_deg:g} deg with k1 = {k1:g}"
    return Loaded(state={"left_raw": images[0], "right_raw": images[1], "calibration": calibration},
                  truth=truth, description=f"synthetic {scene}, {width} x {height}, baseline {baseline:g} m, "
                                           f"{kind}, exact disparity")


# --- a user's folder ------------------------------------------------------------------------------------
#: File stems recognised in a folder (Middlebury's im0/im1/disp0 too).
LEFT_NAMES = ("left", "im0")
RIGHT_NAMES = ("right", "im1")
DISPARITY_NAMES = ("disp", "disp0", "disparity")
CALIBRATION_NAMES = ("calib.yml", "calib.yaml", "calib.json", "calib.txt")

_ALIASES = {
    "K_left": ("k_left", "k1", "m1", "cameramatrix1", "left_k", "cam0", "k"),
    "dist_left": ("dist_left", "d1", "dist1", "distcoeffs1", "left_dist"),
    "K_right": ("k_right", "k2", "m2", "cameramatrix2", "right_k", "cam1"),
    "dist_right": ("dist_right", "d2", "dist2", "distcoeffs2", "right_dist"),
    "R": ("r",),
    "T": ("t",),
    "baseline": ("baseline",),
    "doffs": ("doffs", "disparity_offset"),
}


def _find(directory: str, stems: tuple[str, ...], suffixes: tuple[str, ...]) -> str | None:
    names = {entry.lower(): entry for entry in os.listdir(directory)}
    for stem in stems:
        for suffix in suffixes:
            if stem + suffix in names:
                return os.path.join(directory, names[stem + suffix])
    return None


def read_disparity(path: str) -> np.ndarray:
    """A ground-truth disparity file as ``(H, W)`` float64 pixels with -1 where unknown.

    PFM (Middlebury; ``inf`` unknown) or any image OpenCV reads holding disparities in pixels
    (8- or 16-bit PNG; 0 unknown). Read with :func:`lab.data.files.read_image_file` (the pixel budget,
    then ``cv2.imread``).
    """
    try:
        decoded = read_image_file(path)
    except InvalidValue:
        raise InvalidValue("path", f"{os.path.basename(path)} is not a disparity image OpenCV can read (PNG, "
                                   "PFM ...)") from None
    if decoded.ndim == 3:
        decoded = decoded[:, :, 0]
    values = decoded.astype(np.float64)
    if decoded.dtype.kind == "f":
        return np.where(np.isfinite(values) & (values >= 0), values, -1.0)
    return np.where(values > 0, values, -1.0)


def _normalized_keys(raw: dict[str, Any]) -> dict[str, Any]:
    lower = {str(k).lower(): v for k, v in raw.items()}
    out = {}
    for key, aliases in _ALIASES.items():
        for alias in aliases:
            if alias in lower:
                out[key] = lower[alias]
                break
    return out


def _read_opencv_yaml(path: str) -> dict[str, Any]:
    import cv2

    storage = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    if not storage.isOpened():
        raise InvalidValue("path", f"{os.path.basename(path)} cannot be read as OpenCV YAML")
    try:
        root = storage.root()
        out = {}
        names = root.keys()  # a cv2.FileNode's names (it has no __iter__)
        for key in names:
            out[key] = _node_value(root.getNode(key))
        return out
    finally:
        storage.release()


def _node_value(node: Any) -> Any:
    if node.isMap() and "data" in list(node.keys()):  # !!opencv-matrix
        return node.mat()
    if node.isSeq():
        return [_node_value(node.at(i)) for i in range(node.size())]
    if node.isReal() or node.isInt():
        return node.real()
    if node.isString():
        return node.string()
    return None


def _read_middlebury(path: str) -> dict[str, Any]:
    """Middlebury's ``calib.txt``: ``cam0=[f 0 cx; 0 f cy; 0 0 1]``, ``cam1=...``, ``doffs=``,
    ``baseline=`` (mm)."""
    out: dict[str, Any] = {}
    with open(path, encoding="utf-8") as handle:
        for line in handle:
            if "=" not in line:
                continue
            key, value = (part.strip() for part in line.split("=", 1))
            if value.startswith("["):
                rows = [r.split() for r in value.strip("[]").split(";")]
                out[key] = np.array(rows, dtype=np.float64)
            else:
                try:
                    out[key] = float(value)
                except ValueError:
                    out[key] = value
    if "baseline" in out:
        out["baseline"] = float(out["baseline"]) / 1000.0  # Middlebury gives millimetres
    return out


def read_calibration(path: str) -> StereoCalibration:
    """A stereo calibration file: OpenCV YAML (``cv2.FileStorage``), JSON, or Middlebury's ``calib.txt``.

    Either a full calibration of an unrectified pair (``K1``/``M1``, ``D1``, ``K2``/``M2``, ``D2``,
    ``R``, ``T`` as written by OpenCV's ``stereoCalibrate`` sample; ``T`` in metres) or a rectified
    pair: ``K`` (or ``K1``) and ``baseline`` in metres, with ``doffs`` or ``K2`` for a right principal
    point further right. Raises InvalidValue naming what is missing.
    """
    name = os.path.basename(path)
    try:
        if name.lower().endswith(".json"):
            with open(path, encoding="utf-8") as handle:
                raw = json.load(handle)
        elif name.lower().endswith(".txt"):
            raw = _read_middlebury(path)
        else:
            raw = _read_opencv_yaml(path)
    except (OSError, ValueError, json.JSONDecodeError) as exc:
        raise InvalidValue("path", f"{name} cannot be read: {exc}") from None
    if not isinstance(raw, dict):
        raise InvalidValue("path", f"{name} must hold a mapping of names to values")
    values = _normalized_keys(raw)
    try:
        if "R" in values and "T" in values:
            if "K_left" not in values or "K_right" not in values:
                raise InvalidValue("path", f"{name} has R and T but not both camera matrices (K1/M1 and "
                                           "K2/M2)")
            none = np.zeros(5)  # no distortion given: none
            return StereoCalibration(values["K_left"], values.get("dist_left", none), values["K_right"],
                                     values.get("dist_right", none), values["R"], np.ravel(values["T"]))
        if "K_left" in values and "baseline" in values:
            K = np.asarray(values["K_left"], dtype=np.float64).reshape(3, 3)
            offset = float(values.get("doffs", 0.0))
            if "doffs" not in values and "K_right" in values:
                offset = float(np.asarray(values["K_right"], dtype=np.float64).reshape(3, 3)[0, 2] - K[0, 2])
            return StereoCalibration.rectified(K, float(values["baseline"]), disparity_offset=offset)
    except InvalidValue as exc:
        raise InvalidValue("path", f"{name}: {exc.field}: {exc.reason}") from None
    except (TypeError, ValueError) as exc:
        raise InvalidValue("path", f"{name}: {exc}") from None
    raise InvalidValue("path", f"{name} needs either K and baseline (a rectified pair) or K1, D1, K2, D2, R "
                               f"and T (a calibrated pair to rectify); found {sorted(raw)}")


def folder(*, path: str, downsample: Annotated[int, Range(1, 8)] = 1,
           max_side: Annotated[int, Range(0, 16384)] = WORKING_SIDE) -> Loaded:
    """A user's stereo pair from a folder: ``left.*`` and ``right.*`` (or Middlebury's ``im0``/``im1``).

    Optional files: a calibration (``calib.yml``/``calib.yaml``/``calib.json``/``calib.txt``, see
    :func:`read_calibration`) and, for a rectified pair, a true disparity ``disp.*`` (PNG in pixels
    or PFM; Middlebury's ``disp0.pfm`` too). Without a calibration the pair is taken as rectified
    with ``f`` = the image width and a baseline of 1 (depth then comes in baselines).

    Args:
        path: the folder.
        downsample: integer factor by which to shrink the images (block means), the camera
            matrices and the true disparity; large photos need it to keep the cost volume small.
        max_side: read a pair larger than this on its longer side at this size first
            (:func:`lab.data.files.read_working_images`: a 12-megapixel pair is read at 1600 x 1200, its
            camera matrices and true disparity scaled with it; 0: full resolution).
    """
    directory = check_folder(os.path.expanduser(str(path)))
    left_path = _find(directory, LEFT_NAMES, IMAGE_SUFFIXES)
    right_path = _find(directory, RIGHT_NAMES, IMAGE_SUFFIXES)
    if left_path is None or right_path is None:
        raise InvalidValue("path", f"{path!r} needs a left and a right image named left.* and right.* (or "
                                   f"im0.*, im1.*) in a format OpenCV reads")
    read = read_working_images([left_path, right_path], max_side=int(max_side))
    if read.original_sizes[0] != read.original_sizes[1]:
        (lw, lh), (rw, rh) = read.original_sizes
        raise InvalidValue("path", f"the images differ in size: {os.path.basename(left_path)} is "
                                   f"{lw} x {lh}, {os.path.basename(right_path)} is {rw} x {rh}")
    left, right = read.images
    scale = read.scales[0]
    calibration_path = next((os.path.join(directory, n) for n in os.listdir(directory)
                             if n.lower() in CALIBRATION_NAMES), None)
    if calibration_path is None:
        f = float(left.width)
        K = np.array([[f, 0.0, (left.width - 1) / 2.0], [0.0, f, (left.height - 1) / 2.0], [0.0, 0.0, 1.0]])
        calibration = StereoCalibration.rectified(K, 1.0)
        how = "no calibration: taken as rectified, f = image width, baseline 1"
    else:
        calibration = _scaled_calibration(read_calibration(calibration_path), scale)
        how = f"calibration {os.path.basename(calibration_path)}"
    if read.note:
        how += f"; {read.note}"
    factor = int(downsample)
    if factor > 1:
        if min(left.width, left.height) < 2 * factor:
            raise InvalidValue("downsample", f"the {left.width} x {left.height} images are too small to "
                                             f"shrink {factor} times")
        left, right = (Image(_downsample(im.pixels, factor).astype(np.float32), name=im.name)
                       for im in (left, right))
        calibration = _scaled_calibration(calibration, 1.0 / factor)
    truth: dict[str, Any] = {}
    disparity_path = _find(directory, DISPARITY_NAMES, (*IMAGE_SUFFIXES, ".pfm"))
    if disparity_path is not None:
        if not calibration.is_rectified():
            raise InvalidValue("path", f"{os.path.basename(disparity_path)}: a true disparity goes with a "
                                       "pair that is rectified already, but the calibration describes an "
                                       "unrectified pair")
        disparity = read_disparity(disparity_path)
        if scale != 1.0 and (disparity.shape[1], disparity.shape[0]) == read.original_sizes[0]:
            disparity = _scaled_disparity(disparity, scale, (read.images[0].width, read.images[0].height))
        disparity = _downsample_disparity(disparity, factor)
        if disparity.shape != (left.height, left.width):
            raise InvalidValue("path", f"{os.path.basename(disparity_path)} is {disparity.shape[1]} x "
                                       f"{disparity.shape[0]}, the images {left.width} x {left.height}")
        truth["disparity"] = disparity
    return Loaded(state={"left_raw": left, "right_raw": right, "calibration": calibration}, truth=truth,
                  description=f"{os.path.basename(os.path.normpath(directory))}: {left.width} x "
                              f"{left.height}, {how}" + (", true disparity" if truth else ""))

