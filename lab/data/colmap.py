"""COLMAP's text model (cameras.txt, images.txt, points3D.txt) in and out, exactly.

Format (https://colmap.github.io/format.html#text-format):

* ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``; written as ``PINHOLE`` (``fx fy cx
  cy``), one camera per distinct ``(K, size)``. Read: ``SIMPLE_PINHOLE``, ``PINHOLE``, and the
  distortion models ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV`` when their distortion is zero (a
  :class:`~lab.data.reconstruction.SparseModel` carries no distortion: undistort first).
* ``images.txt``: two lines per image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` (the
  world-to-camera rotation as a unit quaternion, scalar first, and ``t``: COLMAP's
  ``cam_from_world`` is the lab's ``X_c = R X_w + t``) and ``POINTS2D[]`` as ``X Y POINT3D_ID``
  (``-1`` for a keypoint without a 3D point).
* ``points3D.txt``: ``POINT3D_ID X Y Z R G B ERROR TRACK[]`` with the track as ``IMAGE_ID
  POINT2D_IDX`` pairs (``POINT2D_IDX`` is 0-based into the image's ``POINTS2D``).

Conventions converted at this edge (DESIGN.md section 3): COLMAP puts the centre of the top-left
pixel at (0.5, 0.5), the lab at (0, 0), so the principal point and every keypoint gain 0.5 px on
export and lose it on import.

Exact round trip: floats are written with ``repr`` (the shortest string that reads back to the
same double). Adding 0.5 in floating point is not exactly invertible, so shifted values are written
as the shortest decimal ``s`` with ``float(Decimal(s) - 0.5) == value`` and read back with exact
decimal arithmetic. A quaternion does not reproduce a rotation matrix to the last bit either, so
each image line is preceded by a comment ``# R r00 r01 ... r22`` with the exact matrix, which the
reader uses when it agrees with the quaternion (to 1e-9); COLMAP skips comment lines, and other
writers' files are read from the quaternion alone.
"""

from __future__ import annotations

import decimal
from typing import Any
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lab.core.errors import InvalidValue
from lab.data.reconstruction import SparseModel

_HALF = decimal.Decimal("0.5")
_CONTEXT = decimal.Context(prec=1200)  # exact for any double plus one half
_ROTATION_TAG = "# R "


def _repr(value: float) -> str:
    return repr(float(value))


def _to_colmap_pixel(value: float) -> str:
    """``value + 0.5`` as the shortest decimal that :func:`_from_colmap_pixel` maps back to ``value``
    exactly."""
    value = float(value)
    candidate = repr(value + 0.5)
    if float(_CONTEXT.subtract(decimal.Decimal(candidate), _HALF)) == value:
        return candidate
    exact = _CONTEXT.add(decimal.Decimal(value), _HALF)  # the exact decimal of the double plus 0.5
    for digits in range(17, 60):
        text = format(exact, f".{digits}g")
        if float(_CONTEXT.subtract(decimal.Decimal(text), _HALF)) == value:
            return text
    return format(exact, "f")


def _from_colmap_pixel(text: str) -> float:
    return float(_CONTEXT.subtract(decimal.Decimal(text), _HALF))


def _check_name(name: str) -> None:
    if any(ch.isspace() for ch in name):
        raise InvalidValue("names", f"COLMAP's images.txt separates fields by spaces: image name {name!r} "
                                    f"has whitespace")


def write_colmap_text(folder: str | Path, model: SparseModel) -> Path:
    """Write the registered views of ``model`` as a COLMAP text model into ``folder`` (created): cameras.txt,
    images.txt, points3D.txt.

    The model is written as :meth:`~lab.data.reconstruction.SparseModel.compact` gives it: image
    ``i`` (the ``i``-th registered view) gets ``IMAGE_ID = i + 1``, point ``j`` ``POINT3D_ID = j +
    1``; cameras are shared by images with the same ``K`` and size. Raises :class:`InvalidValue` for
    a ``K`` with skew (PINHOLE has none) or image names with whitespace or twice the same. Returns
    the folder.

    ``pycolmap.Reconstruction(folder)`` reads the result (tests check it).
    """
    if not isinstance(model, SparseModel):
        raise InvalidValue("model", f"expected a SparseModel, got {type(model).__name__}")
    rec = model.compact()
    if np.any(rec.K[:, 0, 1] != 0.0):
        raise InvalidValue("K", "COLMAP's PINHOLE camera has no skew, but K[0, 1] != 0 for some image")
    for name in rec.names:
        _check_name(name)
    if len(set(rec.names)) != len(rec.names):
        raise InvalidValue("names", "COLMAP's images.txt names each image once: image names must be unique")
    keypoints, tracks = rec.image_keypoints, rec.tracks
    point_of = [np.full(len(k), -1, dtype=np.int64) for k in keypoints]
    for j, track in enumerate(tracks):
        for image, keypoint in track:
            point_of[image][keypoint] = j + 1

    target = Path(folder)
    target.mkdir(parents=True, exist_ok=True)
    camera_ids: dict[tuple, int] = {}
    camera_lines = []
    image_camera = []
    for K, (width, height) in zip(rec.K, rec.sizes, strict=True):
        key = (int(width), int(height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            camera_lines.append(f"{camera_ids[key]} PINHOLE {key[0]} {key[1]} {_repr(key[2])} "
                                f"{_repr(key[3])} "
                                f"{_to_colmap_pixel(key[4])} {_to_colmap_pixel(key[5])}")
        image_camera.append(camera_ids[key])
    (target / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"# Number of cameras: {len(camera_lines)}\n" + "".join(line + "\n" for line in camera_lines))

    quaternions = Rotation.from_matrix(rec.R).as_quat() if len(rec.R) else np.zeros((0, 4))  # (x, y, z, w)
    quaternions = np.where(quaternions[:, 3:] < 0, -quaternions, quaternions)
    observations = sum(int(np.sum(p >= 0)) for p in point_of)
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(rec)}, mean observations per image: "
             f"{observations / max(len(rec), 1)}",
             "# (lab) a line '# R r00 ... r22' before an image gives its rotation matrix exactly"]
    for i in range(len(rec)):
        qx, qy, qz, qw = quaternions[i]
        lines.append(_ROTATION_TAG + " ".join(_repr(v) for v in rec.R[i].ravel()))
        lines.append(" ".join([str(i + 1), _repr(qw), _repr(qx), _repr(qy), _repr(qz),
                               *(_repr(v) for v in rec.t[i]), str(image_camera[i]), rec.names[i]]))
        lines.append(" ".join(f"{_to_colmap_pixel(u)} {_to_colmap_pixel(v)} {p}"
                              for (u, v), p in zip(keypoints[i], point_of[i], strict=True)))
    (target / "images.txt").write_text("\n".join(lines) + "\n")

    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(rec.points)}, mean track length: {rec.mean_track_length}"]
    for j in range(len(rec.points)):
        elements = " ".join(f"{image + 1} {keypoint}" for image, keypoint in tracks[j])
        lines.append(" ".join([str(j + 1), *(_repr(v) for v in rec.points[j]),
                               *(str(int(c)) for c in rec.colors[j]), _repr(rec.errors[j])])
                     + (" " + elements if elements else ""))
    (target / "points3D.txt").write_text("\n".join(lines) + "\n")
    return target


# --- reading ------------------------------------------------------------------------------------
class _Lines:
    """The data lines of one file with their line numbers (comments and blank lines skipped)."""

    def __init__(self, path: Path) -> None:
        if not path.is_file():
            raise InvalidValue("folder", f"no {path.name} in {str(path.parent)!r}")
        self.path = path
        self.lines = path.read_text().splitlines()

    def error(self, number: int, reason: str) -> InvalidValue:
        return InvalidValue(f"{self.path.name}:{number}", f"{self.path} line {number}: {reason}")


def _read_cameras(path: Path) -> dict[int, tuple[np.ndarray, tuple[int, int]]]:
    source = _Lines(path)
    cameras = {}
    # model -> (number of parameters, focal indices, principal point indices, first distortion index)
    models = {"SIMPLE_PINHOLE": (3, (0, 0), (1, 2), 3), "PINHOLE": (4, (0, 1), (2, 3), 4),
              "SIMPLE_RADIAL": (4, (0, 0), (1, 2), 3), "RADIAL": (5, (0, 0), (1, 2), 3),
              "OPENCV": (8, (0, 1), (2, 3), 4)}
    for number, line in enumerate(source.lines, start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        try:
            camera_id, model, width, height = int(fields[0]), fields[1], int(fields[2]), int(fields[3])
            params = fields[4:]
        except (ValueError, IndexError):
            raise source.error(number, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]") from None
        if model not in models:
            raise source.error(number,
                               f"camera model {model} is not supported; supported are {sorted(models)}")
        count, focal_at, centre_at, distortion_at = models[model]
        if len(params) != count:
            raise source.error(number, f"{model} has {count} parameters, got {len(params)}")
        try:
            fx, fy = float(params[focal_at[0]]), float(params[focal_at[1]])
            cx, cy = _from_colmap_pixel(params[centre_at[0]]), _from_colmap_pixel(params[centre_at[1]])
            distortion = [float(v) for v in params[distortion_at:]]
        except (ValueError, decimal.InvalidOperation):
            raise source.error(number, "camera parameters must be numbers") from None
        if width < 1 or height < 1 or not fx > 0 or not fy > 0:
            raise source.error(number, f"camera {camera_id} needs a positive size and focal length")
        if any(distortion):
            raise source.error(number,
                               f"camera {camera_id} ({model}) has lens distortion {distortion}, which a "
                               f"SparseModel does not carry: undistort the images first "
                               f"(colmap image_undistorter)")
        if camera_id in cameras:
            raise source.error(number, f"camera id {camera_id} appears twice")
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        cameras[camera_id] = (K, (width, height))
    return cameras


def _read_images(path: Path,
                 cameras: dict[int, tuple[np.ndarray, tuple[int, int]]]) -> dict[int, tuple[Any, ...]]:
    """images.txt: ``{image id: (R, t, camera id, name, keypoints, point ids, line number)}``."""
    source = _Lines(path)
    images = {}  # image id -> (R, t, camera id, name, keypoints, point ids, line number)
    pending_rotation = None
    lines = source.lines
    number = 0
    while number < len(lines):
        line = lines[number].strip()
        number += 1
        if line.startswith(_ROTATION_TAG):
            try:
                entries = [float(v) for v in line[len(_ROTATION_TAG):].split()]
                pending_rotation = np.array(entries).reshape(3, 3)
            except ValueError:
                pending_rotation = None
            continue
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        try:
            image_id = int(fields[0])
            q = np.array([float(v) for v in fields[1:5]])
            t = np.array([float(v) for v in fields[5:8]])
            camera_id = int(fields[8])
            name = fields[9]
        except (ValueError, IndexError):
            raise source.error(number, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME") from None
        if len(fields) != 10:
            raise source.error(number,
                               f"expected 10 fields, got {len(fields)} (image names cannot contain spaces)")
        if camera_id not in cameras:
            raise source.error(number, f"camera id {camera_id} is not in cameras.txt")
        if image_id in images:
            raise source.error(number, f"image id {image_id} appears twice")
        if not np.all(np.isfinite(q)) or np.linalg.norm(q) == 0:
            raise source.error(number, "the quaternion must be finite and non-zero")
        R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        if pending_rotation is not None and np.all(np.isfinite(pending_rotation)) \
                and np.max(np.abs(pending_rotation - R)) < 1e-9:
            R = pending_rotation
        pending_rotation = None
        points_line = lines[number] if number < len(lines) else ""
        number += 1
        values = points_line.split()
        if len(values) % 3:
            raise source.error(number, f"POINTS2D must be triples X Y POINT3D_ID, got {len(values)} numbers")
        try:
            keypoints = np.array([[_from_colmap_pixel(values[k]), _from_colmap_pixel(values[k + 1])]
                                  for k in range(0, len(values), 3)]).reshape(-1, 2)
            point_ids = np.array([int(values[k + 2]) for k in range(0, len(values), 3)], dtype=np.int64)
        except (ValueError, decimal.InvalidOperation):
            raise source.error(number, "POINTS2D must be numbers X Y and an integer POINT3D_ID") from None
        images[image_id] = (R, t, camera_id, name, keypoints, point_ids, number)
    return images


def _read_points(path: Path, images: dict[int, tuple[Any, ...]]) -> dict[int, tuple[Any, ...]]:
    """points3D.txt: ``{point id: (xyz, rgb, error, track as (image index, keypoint) rows)}``, checked
    against the images' ``POINT3D_ID``."""
    index_of = {image_id: i for i, image_id in enumerate(sorted(images))}
    points_source = _Lines(path)
    points = {}
    for number, line in enumerate(points_source.lines, start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        try:
            point_id = int(fields[0])
            xyz = [float(v) for v in fields[1:4]]
            rgb = [int(v) for v in fields[4:7]]
            error = float(fields[7])
            track = np.array([int(v) for v in fields[8:]], dtype=np.int64)
        except (ValueError, IndexError):
            raise points_source.error(number, "expected POINT3D_ID X Y Z R G B ERROR TRACK[]") from None
        if len(track) % 2:
            raise points_source.error(number, "TRACK[] must be pairs IMAGE_ID POINT2D_IDX")
        if point_id in points:
            raise points_source.error(number, f"point id {point_id} appears twice")
        if any(c < 0 or c > 255 for c in rgb):
            raise points_source.error(number, f"colour {rgb} is outside [0, 255]")
        track = track.reshape(-1, 2)
        converted = np.empty_like(track)
        for k, (image_id, keypoint) in enumerate(track):
            if image_id not in images:
                raise points_source.error(number, f"image id {image_id} is not in images.txt")
            image = images[image_id]
            if not 0 <= keypoint < len(image[4]) or image[5][keypoint] != point_id:
                raise points_source.error(number,
                                          f"observation ({image_id}, {keypoint}) does not match images.txt "
                                          f"(POINT3D_ID there: "
                                          f"{image[5][keypoint] if 0 <= keypoint < len(image[5]) else 'none'}"
                                          ")")
            converted[k] = (index_of[image_id], keypoint)
        points[point_id] = (xyz, rgb, error, converted)
    return points


def read_colmap_text(folder: str | Path) -> SparseModel:
    """Read a COLMAP text model (cameras.txt, images.txt, points3D.txt) from ``folder``.

    Images are ordered by ``IMAGE_ID`` (all registered), points by ``POINT3D_ID`` (each its own
    track, :meth:`~lab.data.reconstruction.SparseModel.from_tracks`).
    Pixels move by -0.5 to the lab's convention (module docstring). Raises :class:`InvalidValue`
    naming the file and line of anything malformed, an unknown camera or image id, a track that
    disagrees with the images' ``POINT3D_ID``, or a camera with lens distortion.

    Reads what ``pycolmap.Reconstruction.write_text`` writes (rigs.txt and frames.txt, if
    present, are ignored: one camera per image).
    """
    root = Path(folder)
    if not root.is_dir():
        raise InvalidValue("folder", f"no such folder: {str(root)!r}")
    cameras = _read_cameras(root / "cameras.txt")
    images = _read_images(root / "images.txt", cameras)
    points = _read_points(root / "points3D.txt", images)
    order, point_order = sorted(images), sorted(points)
    return SparseModel.from_tracks(
        K=np.array([cameras[images[i][2]][0] for i in order]).reshape(-1, 3, 3),
        sizes=np.array([cameras[images[i][2]][1] for i in order], dtype=np.int64).reshape(-1, 2),
        R=np.array([images[i][0] for i in order]).reshape(-1, 3, 3),
        t=np.array([images[i][1] for i in order]).reshape(-1, 3),
        names=tuple(images[i][3] for i in order),
        keypoints=tuple(images[i][4] for i in order),
        points=np.array([points[p][0] for p in point_order], dtype=np.float64).reshape(-1, 3),
        colors=np.array([points[p][1] for p in point_order], dtype=np.uint8).reshape(-1, 3),
        errors=np.array([points[p][2] for p in point_order], dtype=np.float64),
        tracks=tuple(points[p][3] for p in point_order),
    )


__all__ = ["read_colmap_text", "write_colmap_text"]
