"""``transforms.json`` (nerfstudio / instant-ngp) out and in: the one reader the NeRF module uses.

The file (nerfstudio's "data conventions", instant-ngp's ``scripts/colmap2nerf.py``)::

    {"camera_model": "OPENCV", "fl_x": ..., "fl_y": ..., "cx": ..., "cy": ..., "w": 640, "h": 480,
     "k1": 0, "k2": 0, "p1": 0, "p2": 0, "camera_angle_x": ..., "camera_angle_y": ...,
     "frames": [{"file_path": "images/view_00.png", "transform_matrix": [[4 x 4]]}, ...]}

Intrinsics are global when every image shares them, else per frame (the same keys inside each
frame). ``transform_matrix`` is the camera-to-world matrix of an OpenGL camera (x right, y up,
z backwards): ``[R^T | -R^T t]`` of the lab's OpenCV camera with its y and z axes flipped, i.e.
``c2w_gl = c2w_cv @ diag(1, -1, -1, 1)``. Pixel centres: like COLMAP (which both tools convert
from), nerfstudio and instant-ngp put the centre of the top-left pixel at (0.5, 0.5), so ``cx``,
``cy`` are the lab's plus 0.5.

Reading accepts either tool's variants: global or per-frame intrinsics, ``camera_angle_x`` (and
``camera_angle_y``) instead of focal lengths, a missing principal point (the image centre), and a
``3 x 4`` or ``4 x 4`` matrix. The world frame is whatever the file uses; nothing is re-centred.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from lab.core.errors import InvalidValue
from lab.data.reconstruction import SparseModel
from lab.geometry.rotations import nearest_rotation

#: OpenCV camera axes -> OpenGL camera axes (flip y and z), acting on the right of camera-to-world.
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")


def camera_to_world_opengl(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world ``(N, 4, 4)`` of world-to-camera OpenCV poses ``R`` ``(N, 3, 3)``,
    ``t`` ``(N, 3)``."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    c2w = np.zeros((*R.shape[:-2], 4, 4))
    c2w[..., :3, :3] = np.swapaxes(R, -1, -2)
    c2w[..., :3, 3] = -np.einsum("...ji,...j->...i", R, t)
    c2w[..., 3, 3] = 1.0
    return c2w @ OPENCV_TO_OPENGL


def write_transforms_json(path: str | Path, model: SparseModel, *, image_folder: str = "images",
                          points_ply: str | None = None) -> Path:
    """Write the registered cameras of ``model`` as a nerfstudio / instant-ngp ``transforms.json`` at
    ``path``.

    Args:
        path: the file to write (parent folders are created).
        model: the reconstruction (its points are not in the JSON); frame ``i`` is its ``i``-th
            registered view.
        image_folder: folder of the images relative to the file; a frame's ``file_path`` is
            ``f"{image_folder}/{name}"`` (just the name when ``image_folder`` is "").
        points_ply: if given, a PLY file name (relative to the JSON) to write the points with their
            colours to, referenced as ``ply_file_path`` (nerfstudio's splatting initialisation).

    Raises :class:`InvalidValue` for a ``K`` with skew (the format has none). Returns the path.
    """
    if not isinstance(model, SparseModel):
        raise InvalidValue("model", f"expected a SparseModel, got {type(model).__name__}")
    views = np.flatnonzero(model.registered)
    rec_K, rec_sizes, rec_names = model.K[views], model.sizes[views], tuple(model.names[v] for v in views)
    if np.any(rec_K[:, 0, 1] != 0.0):
        raise InvalidValue("K", "transforms.json has no skew, but K[0, 1] != 0 for some image")
    intrinsics = [{"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]) + 0.5,
                   "cy": float(K[1, 2]) + 0.5, "w": int(w), "h": int(h)}
                  for K, (w, h) in zip(rec_K, rec_sizes, strict=True)]
    shared = all(entry == intrinsics[0] for entry in intrinsics)
    data: dict = {"camera_model": "OPENCV"}
    if shared and intrinsics:
        data.update(intrinsics[0])
        data["camera_angle_x"] = 2.0 * math.atan(0.5 * intrinsics[0]["w"] / intrinsics[0]["fl_x"])
        data["camera_angle_y"] = 2.0 * math.atan(0.5 * intrinsics[0]["h"] / intrinsics[0]["fl_y"])
    data.update({"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
    c2w = camera_to_world_opengl(model.R[views], model.t[views])
    frames = []
    for i, name in enumerate(rec_names):
        frame: dict = {"file_path": f"{image_folder.rstrip('/')}/{name}" if image_folder else name,
                       "transform_matrix": c2w[i].tolist()}
        if not shared:
            frame.update(intrinsics[i])
        frames.append(frame)
    data["frames"] = frames
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    if points_ply:
        from lab.core.codecs import to_ply

        (target.parent / points_ply).write_bytes(to_ply(model.point_cloud(), name="xyz"))
        data["ply_file_path"] = points_ply
    target.write_text(json.dumps(data, indent=2) + "\n")
    return target


def _number(container: dict, key: str, where: str) -> float:
    value = container[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InvalidValue(where, f"{key!r} must be a finite number, got {value!r}")
    return float(value)


def _intrinsics(frame: dict, top: dict, where: str,
                default_size: tuple[int, int] | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """K (lab convention) and (w, h) of one frame, per-frame keys overriding global ones; ``default_size``
    stands in for a missing ``w`` and ``h``."""
    def get(key: str):
        return frame[key] if key in frame else top.get(key)

    keys = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "camera_model",
            *_DISTORTION_KEYS)
    merged = {key: get(key) for key in keys if get(key) is not None}
    model = merged.get("camera_model", "OPENCV")
    if model not in _PINHOLE_MODELS:
        raise InvalidValue(where,
                           f"camera_model {model!r} is not a pinhole model ({', '.join(_PINHOLE_MODELS)})")
    distortion = {key: merged[key] for key in _DISTORTION_KEYS if key in merged}
    if any(_number(merged, key, where) != 0.0 for key in distortion):
        raise InvalidValue(where, f"the camera has lens distortion {distortion}: undistort the images first "
                                  f"(the lab's cameras are pinhole)")
    if default_size is not None:
        merged.setdefault("w", default_size[0])
        merged.setdefault("h", default_size[1])
    for key in ("w", "h"):
        if key not in merged:
            raise InvalidValue(where, f"no image size: {key!r} is missing")
    w, h = _number(merged, "w", where), _number(merged, "h", where)
    if w < 1 or h < 1 or w != int(w) or h != int(h):
        raise InvalidValue(where, f"image size must be positive integers, got w={w}, h={h}")
    if "fl_x" in merged:
        fx = _number(merged, "fl_x", where)
    elif "camera_angle_x" in merged:
        fx = 0.5 * w / math.tan(0.5 * _number(merged, "camera_angle_x", where))
    else:
        raise InvalidValue(where, "no focal length: neither 'fl_x' nor 'camera_angle_x'")
    if "fl_y" in merged:
        fy = _number(merged, "fl_y", where)
    elif "camera_angle_y" in merged:
        fy = 0.5 * h / math.tan(0.5 * _number(merged, "camera_angle_y", where))
    else:
        fy = fx
    if not (fx > 0 and fy > 0):
        raise InvalidValue(where, f"focal lengths must be positive, got fl_x={fx}, fl_y={fy}")
    cx = _number(merged, "cx", where) if "cx" in merged else 0.5 * w
    cy = _number(merged, "cy", where) if "cy" in merged else 0.5 * h
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return K, (int(w), int(h))


def read_transforms_json(path: str | Path, *, default_size: tuple[int, int] | None = None,
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """Read a nerfstudio / instant-ngp ``transforms.json`` into the lab's conventions.

    Returns ``K`` ``(N, 3, 3)`` (principal point moved by -0.5 px to the lab's pixel centres),
    ``sizes`` ``(N, 2)`` int ``(width, height)``, ``R`` ``(N, 3, 3)`` and ``t`` ``(N, 3)``
    world-to-camera in the OpenCV convention (``X_c = R X_w + t``), and the frames' ``file_path``
    values as written (relative to the file's folder), in file order.

    The rotation block of each ``transform_matrix`` must be a rotation (to 1e-6; instant-ngp
    files that scale it are rejected) and is re-orthonormalized. Raises :class:`InvalidValue`
    naming the frame for a missing size (unless ``default_size`` ``(w, h)`` gives it: the NeRF-synthetic
    Blender files state only ``camera_angle_x``, the size is their images'), a missing focal length, lens
    distortion, a non-pinhole camera model, or a malformed matrix.
    """
    source = Path(path)
    if not source.is_file():
        raise InvalidValue("path", f"no such file: {str(source)!r}")
    try:
        data = json.loads(source.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InvalidValue("path", f"{str(source)!r} is not JSON: {exc}") from None
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames:
        raise InvalidValue("frames", f"{str(source)!r} has no 'frames' list")
    Ks, sizes, Rs, ts, names = [], [], [], [], []
    for index, frame in enumerate(frames):
        where = f"frames[{index}]"
        if not isinstance(frame, dict) or "transform_matrix" not in frame or "file_path" not in frame:
            raise InvalidValue(where, "each frame needs 'file_path' and 'transform_matrix'")
        K, size = _intrinsics(frame, data, where, default_size)
        try:
            matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise InvalidValue(where,
                               "transform_matrix must be a 4 x 4 (or 3 x 4) array of numbers") from None
        if matrix.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(matrix)):
            raise InvalidValue(where,
                               "transform_matrix must be a finite 4 x 4 (or 3 x 4) matrix, got "
                               f"{matrix.shape}")
        c2w_gl = np.eye(4)
        c2w_gl[:3] = matrix[:3]
        c2w = c2w_gl @ OPENCV_TO_OPENGL  # the flip is its own inverse
        rotation = c2w[:3, :3]
        if np.max(np.abs(rotation @ rotation.T - np.eye(3))) > 1e-6 or np.linalg.det(rotation) < 0:
            raise InvalidValue(where, "the rotation block of transform_matrix is not a rotation (scaled or "
                                      "reflected camera-to-world matrices are not supported)")
        R = nearest_rotation(rotation).T
        Ks.append(K)
        sizes.append(size)
        Rs.append(R)
        ts.append(-R @ c2w[:3, 3])
        names.append(str(frame["file_path"]))
    return np.array(Ks), np.array(sizes, dtype=np.int64), np.array(Rs), np.array(ts), tuple(names)


__all__ = ["OPENCV_TO_OPENGL", "camera_to_world_opengl", "read_transforms_json", "write_transforms_json"]
