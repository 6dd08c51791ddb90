"""Writing state values to files: JSON, NPY, PNG, PLY and OpenCV's YAML calibration files.

Exports convert at the edge, never inside a step (DESIGN.md section 3). The value encodings are
:mod:`lab.core.codecs` (the same bytes the REST API serves); this module only adds files and
OpenCV's calibration format, written and read with ``cv2.FileStorage`` so that any OpenCV program
(``cv::FileStorage fs("camera.yaml", cv::FileStorage::READ); fs["camera_matrix"] >> K;``) reads
it, with the node names of OpenCV's own calibration sample (samples/cpp/calibration.cpp).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lab.core import codecs
from lab.core.errors import InvalidValue

#: Formats :func:`write_value` writes, and the file suffix each usually has.
VALUE_FORMATS: dict[str, str] = {"json": ".json", "npy": ".npy", "png": ".png", "ply": ".ply"}

#: Formats :func:`write_reconstruction` writes a :class:`~lab.data.reconstruction.SparseModel`
#: in, and what ``path`` names for each.
RECONSTRUCTION_FORMATS: dict[str, str] = {
    "colmap": "a folder: COLMAP text model (cameras.txt, images.txt, points3D.txt)",
    "transforms-json": "a file: nerfstudio / instant-ngp transforms.json (OpenGL camera-to-world)",
}


def write_value(path: str | Path, value: Any, fmt: str, *, name: str, index: int | None = None) -> Path:
    """Write one state value to ``path`` in ``fmt`` (json, npy, png or ply) through the codecs.

    ``index`` picks one view of an :class:`~lab.core.values.ImageSet` for png/npy. Missing parent
    folders are created. Raises :class:`InvalidValue` (field ``format``) when the value has no such
    form (e.g. PLY of an image).
    """
    if fmt not in VALUE_FORMATS:
        raise InvalidValue("format", f"unknown format {fmt!r}; formats are {list(VALUE_FORMATS)}")
    encoded = codecs.encode(value, fmt, name=name, index=index)
    payload = (json.dumps(encoded) + "\n").encode() if fmt == "json" else encoded
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(payload)
    return target


def file_names(names: tuple[str, ...], registered: np.ndarray) -> tuple[str, ...]:
    """Image names made file names: whitespace becomes ``_``, and a name a registered view before had
    already is prefixed with its view index (``003_name``)."""
    out = []
    taken: set[str] = set()
    for v, name in enumerate(names):
        name = "".join(c if not c.isspace() else "_" for c in name)
        if registered[v]:
            name = name if name not in taken else f"{v:03d}_{name}"
            taken.add(name)
        out.append(name)
    return tuple(out)


def write_reconstruction(path: str | Path, model: Any, fmt: str, *, image_folder: str = "images") -> Path:
    """Write a sparse reconstruction in ``fmt`` (a key of :data:`RECONSTRUCTION_FORMATS`).

    Its registered views are written (:meth:`~lab.data.reconstruction.SparseModel.compact`), their
    names made file names (:func:`file_names`). ``colmap``: :func:`lab.data.colmap.write_colmap_text`
    into the folder ``path``; ``transforms-json``: :func:`lab.data.transforms_json.write_transforms_json`
    to the file ``path`` (frames at ``image_folder/<name>``). Raises :class:`InvalidValue` (field
    ``format``) for another format or a value that is not a SparseModel.
    """
    from dataclasses import replace

    from lab.data.reconstruction import SparseModel

    if fmt not in RECONSTRUCTION_FORMATS:
        raise InvalidValue("format", f"unknown format {fmt!r}; reconstruction formats are "
                                     f"{list(RECONSTRUCTION_FORMATS)}")
    if not isinstance(model, SparseModel):
        raise InvalidValue("format", f"{fmt} writes a SparseModel, not a {type(model).__name__}")
    model = replace(model, names=file_names(model.names, model.registered))
    if fmt == "colmap":
        from lab.data.colmap import write_colmap_text

        return write_colmap_text(path, model)
    from lab.data.transforms_json import write_transforms_json

    return write_transforms_json(path, model, image_folder=image_folder)


@dataclass(frozen=True)
class OpenCVCalibration:
    """What an OpenCV calibration file holds: ``K`` (3, 3), ``dist`` (k1, k2, p1, p2, k3) and more."""

    K: np.ndarray
    dist: np.ndarray
    image_width: int
    image_height: int
    avg_reprojection_error: float | None = None


def write_opencv_calibration(path: str | Path, K: np.ndarray, dist: np.ndarray, *, image_width: int,
                             image_height: int, avg_reprojection_error: float | None = None,
                             per_view_reprojection_errors: np.ndarray | list[float] | None = None,
                             board_width: int | None = None, board_height: int | None = None,
                             square_size: float | None = None, rotations: np.ndarray | None = None,
                             translations: np.ndarray | None = None) -> Path:
    """Write intrinsics as OpenCV's calibration sample does, in YAML through ``cv2.FileStorage``.

    Nodes: ``calibration_time``, ``nframes`` (with per-view errors or poses), ``image_width``,
    ``image_height``, ``board_width``/``board_height``/``square_size`` (when given),
    ``camera_matrix`` (3x3 double), ``distortion_coefficients`` (5x1 double: k1, k2, p1, p2, k3),
    ``avg_reprojection_error`` (px), ``per_view_reprojection_errors`` (Vx1) and
    ``extrinsic_parameters`` (Vx6: Rodrigues vector, translation; board -> camera) from
    ``rotations`` (V, 3, 3) and ``translations`` (V, 3). The file is YAML whatever its suffix.
    """
    import cv2

    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InvalidValue("K", f"expected a finite (3, 3) camera matrix, got shape {K.shape}")
    if dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise InvalidValue("dist",
                           f"expected 4, 5, 8, 12 or 14 finite distortion coefficients, got {dist.size}")
    if int(image_width) < 1 or int(image_height) < 1:
        raise InvalidValue("image_size", f"must be positive, got {image_width}x{image_height}")
    extrinsics = None
    if rotations is not None and translations is not None:
        rotations = np.asarray(rotations, dtype=np.float64)
        translations = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
        if rotations.shape != (len(translations), 3, 3):
            raise InvalidValue("rotations", f"expected ({len(translations)}, 3, 3), got {rotations.shape}")
        extrinsics = np.array([np.concatenate([cv2.Rodrigues(R)[0].ravel(), t])
                               for R, t in zip(rotations, translations, strict=True)]).reshape(-1, 6)
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    storage = cv2.FileStorage(str(target), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    if not storage.isOpened():
        raise InvalidValue("out", f"cannot open {str(target)!r} for writing")
    try:
        storage.write("calibration_time", time.strftime("%a %b %d %H:%M:%S %Y"))
        if extrinsics is not None:
            storage.write("nframes", len(extrinsics))
        elif per_view_reprojection_errors is not None:
            storage.write("nframes", len(per_view_reprojection_errors))
        storage.write("image_width", int(image_width))
        storage.write("image_height", int(image_height))
        if board_width is not None and board_height is not None:
            storage.write("board_width", int(board_width))
            storage.write("board_height", int(board_height))
        if square_size is not None:
            storage.write("square_size", float(square_size))
        storage.write("camera_matrix", K)
        storage.write("distortion_coefficients", dist.reshape(-1, 1))
        if avg_reprojection_error is not None:
            storage.write("avg_reprojection_error", float(avg_reprojection_error))
        if per_view_reprojection_errors is not None:
            storage.write("per_view_reprojection_errors",
                          np.asarray(per_view_reprojection_errors, dtype=np.float64).reshape(-1, 1))
        if extrinsics is not None:
            storage.write("extrinsic_parameters", extrinsics)
    finally:
        storage.release()
    return target


def read_opencv_calibration(path: str | Path) -> OpenCVCalibration:
    """Read a calibration file written by :func:`write_opencv_calibration` or by OpenCV's tools.

    Raises :class:`InvalidValue` when the file is missing or lacks ``camera_matrix`` /
    ``distortion_coefficients``.
    """
    import cv2

    source = Path(path)
    if not source.is_file():
        raise InvalidValue("path", f"no such file: {str(source)!r}")
    try:
        storage = cv2.FileStorage(str(source), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise InvalidValue("path",
                           f"{str(source)!r} is not an OpenCV YAML/XML/JSON file ({exc.err})") from None
    try:
        K = storage.getNode("camera_matrix").mat()
        dist = storage.getNode("distortion_coefficients").mat()
        if K is None or dist is None:
            raise InvalidValue("path", f"{str(source)!r} has no camera_matrix or distortion_coefficients")
        rms_node = storage.getNode("avg_reprojection_error")
        return OpenCVCalibration(
            K=np.asarray(K, dtype=np.float64).reshape(3, 3),
            dist=np.asarray(dist, dtype=np.float64).reshape(-1),
            image_width=int(storage.getNode("image_width").real()),
            image_height=int(storage.getNode("image_height").real()),
            avg_reprojection_error=None if rms_node.empty() else float(rms_node.real()),
        )
    finally:
        storage.release()


__all__ = [
    "RECONSTRUCTION_FORMATS", "VALUE_FORMATS", "OpenCVCalibration", "file_names", "read_opencv_calibration",
    "write_opencv_calibration", "write_reconstruction", "write_value",
]
