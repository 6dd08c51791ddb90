"""Codecs for state values: JSON, NPY, PNG and PLY out; JSON, NPY and image files in.

The JSON form of a typed value is derived from its dataclass fields (viser's lesson: one
dataclass is the single source of truth for the wire format): ``{"type": "Points2D", "xy":
[[...]], ...}``; arrays become nested lists. ``decode_json`` reverses it for uploads.
"""

from __future__ import annotations

import dataclasses
import io
import typing
from typing import Any

import numpy as np

from lab.core.errors import InvalidValue
from lab.core.values import VALUE_TYPES, Cameras, Curve, Image, ImageSet, Mesh, PointCloud, Points2D

FORMATS = ("json", "npy", "png", "ply")


# --- JSON ---------------------------------------------------------------------------------------
def to_json(value: Any) -> Any:
    """A JSON-ready form of any state value."""
    if isinstance(value, np.ndarray):
        if value.dtype.kind == "b":
            return value.tolist()
        return np.where(np.isfinite(value), value, None).tolist() if value.dtype.kind == "f" else value.tolist()
    if isinstance(value, (np.floating, float)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        out: dict[str, Any] = {"type": type(value).__name__}
        for f in dataclasses.fields(value):
            out[f.name] = to_json(getattr(value, f.name))
        return out
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    return value


def decode_json(data: Any, annotation: Any, *, name: str) -> Any:
    """Build a state value of type ``annotation`` from uploaded JSON (raises InvalidValue)."""
    cls = _base_type(annotation)
    try:
        if cls is np.ndarray:
            array = np.asarray(data, dtype=np.float64)
            if array.dtype == object:
                raise ValueError("ragged or non-numeric")
            if not np.all(np.isfinite(array)):
                raise InvalidValue(name, "contains NaN or infinite entries")
            return array
        if cls in (float, int, bool, str):
            if not isinstance(data, (int, float, str, bool)):
                raise InvalidValue(name, f"expected a {cls.__name__}")
            return cls(data)
        if cls is ImageSet:
            if isinstance(data, dict):
                data = data.get("images")
            if not isinstance(data, list):
                raise InvalidValue(name, "an ImageSet is a list of images")
            return ImageSet(tuple(decode_json(d, Image, name=f"{name}[{i}]") for i, d in enumerate(data)))
        if cls in VALUE_TYPES.values() or dataclasses.is_dataclass(cls):
            if isinstance(data, list) and cls in (Points2D, PointCloud):
                data = {"xy" if cls is Points2D else "xyz": data}
            if not isinstance(data, dict):
                raise InvalidValue(name, f"expected a JSON object for {cls.__name__}")
            data = {k: v for k, v in data.items() if k != "type"}
            hints = typing.get_type_hints(cls)
            known = {f.name for f in dataclasses.fields(cls)}
            unknown = set(data) - known
            if unknown:
                raise InvalidValue(name, f"{cls.__name__} has no field(s) {sorted(unknown)}; fields are {sorted(known)}")
            kwargs = {}
            for key, item in data.items():
                sub = _base_type(hints.get(key))
                if sub is not None and dataclasses.is_dataclass(sub):
                    kwargs[key] = decode_json(item, sub, name=f"{name}.{key}")
                elif sub is tuple or typing.get_origin(hints.get(key)) is tuple:
                    kwargs[key] = tuple(item)
                else:
                    kwargs[key] = item
            return cls(**kwargs)
    except InvalidValue as exc:
        raise InvalidValue(name if exc.field in ("pixels", "xy", "xyz") else f"{name}.{exc.field}"
                           if not exc.field.startswith(name) else exc.field, exc.reason) from None
    except (TypeError, ValueError) as exc:
        raise InvalidValue(name, f"cannot be read as {getattr(cls, '__name__', cls)}: {exc}") from None
    return data


def _base_type(annotation: Any) -> Any:
    """``X | None`` -> ``X``; ``Annotated[X, ...]`` -> ``X``."""
    if annotation is None:
        return None
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _base_type(typing.get_args(annotation)[0])
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if origin is not None and len(args) == 1 and type(None) in typing.get_args(annotation):
        return _base_type(args[0])
    if origin is not None and origin is not tuple:
        return origin
    return annotation


# --- NPY ----------------------------------------------------------------------------------------
_PRIMARY = {Image: "pixels", Points2D: "xy", PointCloud: "xyz", Mesh: "vertices", Curve: "y"}


def primary_array(value: Any, *, name: str, index: int | None = None) -> np.ndarray:
    """The array a typed value is about (an image's pixels, a point cloud's xyz, ...)."""
    if isinstance(value, np.ndarray):
        return value
    if isinstance(value, (int, float, np.number, bool)):
        return np.asarray(value)
    if isinstance(value, ImageSet):
        if index is None:
            shapes = {im.pixels.shape for im in value.images}
            if len(shapes) != 1:
                raise InvalidValue("index", f"{name!r} holds images of different sizes: ask for one with ?index=")
            return np.stack([im.pixels for im in value.images])
        return value[_index(value, index, name)].pixels
    if isinstance(value, Cameras):
        return np.concatenate([value.R, value.t[:, :, None]], axis=2)  # (V, 3, 4) [R | t]
    for cls, attr in _PRIMARY.items():
        if isinstance(value, cls):
            return getattr(value, attr)
    raise InvalidValue("format", f"{name!r} ({type(value).__name__}) has no NPY form; use format=json")


def _index(images: ImageSet, index: int, name: str) -> int:
    if not 0 <= index < len(images):
        raise InvalidValue("index", f"{name!r} has {len(images)} views; index must be in [0, {len(images) - 1}]")
    return index


def to_npy(value: Any, *, name: str, index: int | None = None) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, primary_array(value, name=name, index=index), allow_pickle=False)
    return buffer.getvalue()


def from_npy(payload: bytes, *, name: str) -> np.ndarray:
    try:
        array = np.load(io.BytesIO(payload), allow_pickle=False)
    except Exception as exc:  # numpy raises ValueError, OSError, EOFError... on bad files
        raise InvalidValue(name, f"not a valid .npy file ({type(exc).__name__}: {exc})") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "biuf":
        raise InvalidValue(name, f"a .npy upload must hold a numeric array, got dtype {getattr(array, 'dtype', '?')}")
    return array


# --- PNG / images ---------------------------------------------------------------------------------
def to_png(value: Any, *, name: str, index: int | None = None) -> bytes:
    import cv2

    if isinstance(value, ImageSet):
        value = value[_index(value, 0 if index is None else index, name)]
    if isinstance(value, Image):
        pixels = value.pixels
    elif isinstance(value, np.ndarray) and value.ndim in (2, 3) and value.dtype.kind in "fui":
        pixels = value.astype(np.float32)
        if value.dtype.kind == "f":
            lo, hi = float(np.nanmin(pixels)), float(np.nanmax(pixels))
            if lo < 0 or hi > 1:  # e.g. a disparity map: stretch to [0, 1] for display
                pixels = (pixels - lo) / (hi - lo if hi > lo else 1.0)
        else:
            pixels = pixels / 255.0
    else:
        raise InvalidValue("format", f"{name!r} ({type(value).__name__}) is not an image; use format=json")
    rgb = np.clip(np.nan_to_num(pixels) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if rgb.ndim == 3:
        rgb = rgb[:, :, ::-1]  # OpenCV writes BGR
    ok, encoded = cv2.imencode(".png", rgb)
    if not ok:  # pragma: no cover
        raise InvalidValue(name, "could not encode PNG")
    return encoded.tobytes()


def decode_image(payload: bytes, *, name: str) -> Image:
    """An uploaded image file (any format OpenCV reads) as an :class:`Image` (RGB float32 in [0, 1])."""
    import cv2

    data = np.frombuffer(payload, dtype=np.uint8)
    decoded = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if len(data) else None
    if decoded is None:
        raise InvalidValue(name, "the upload is not an image file OpenCV can read (PNG, JPEG, TIFF, BMP ...)")
    return image_from_cv2(decoded, name=name)


def image_from_cv2(decoded: np.ndarray, *, name: str = "") -> Image:
    """Convert an array from ``cv2.imread``/``imdecode`` (BGR, any depth) to an :class:`Image`."""
    import cv2

    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(decoded.dtype, 1.0)
    pixels = decoded.astype(np.float32) / scale
    if pixels.ndim == 3 and pixels.shape[2] == 4:
        pixels = pixels[:, :, :3]
    if pixels.ndim == 3 and pixels.shape[2] == 3:
        pixels = cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB)
    return Image(np.clip(pixels, 0.0, 1.0), name=name)


# --- PLY ----------------------------------------------------------------------------------------
def to_ply(value: Any, *, name: str) -> bytes:
    """Binary PLY of a point cloud (with colours) or a mesh, through trimesh."""
    import trimesh

    if isinstance(value, PointCloud):
        colors = None if value.colors is None else np.clip(value.colors * 255 + 0.5, 0, 255).astype(np.uint8)
        geometry = trimesh.PointCloud(value.xyz, colors=colors)
    elif isinstance(value, Mesh):
        colors = None if value.vertex_colors is None else np.clip(value.vertex_colors * 255 + 0.5, 0, 255).astype(np.uint8)
        geometry = trimesh.Trimesh(value.vertices, value.faces, vertex_colors=colors, process=False)
    elif isinstance(value, np.ndarray) and value.ndim == 2 and value.shape[1] == 3:
        geometry = trimesh.PointCloud(value)
    else:
        raise InvalidValue("format", f"{name!r} ({type(value).__name__}) is not a point cloud or mesh; use format=json")
    return geometry.export(file_type="ply")


def from_ply(payload: bytes, *, name: str) -> PointCloud | Mesh:
    import trimesh

    try:
        loaded = trimesh.load(io.BytesIO(payload), file_type="ply", process=False)
    except Exception as exc:
        raise InvalidValue(name, f"not a readable PLY file ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Trimesh):
        colors = getattr(loaded.visual, "vertex_colors", None)
        return Mesh(loaded.vertices, loaded.faces,
                    None if colors is None else np.asarray(colors)[:, :3] / 255.0)
    colors = getattr(loaded, "colors", None)
    colors = None if colors is None or len(colors) == 0 else np.asarray(colors)[:, :3] / 255.0
    return PointCloud(np.asarray(loaded.vertices), colors)


MEDIA_TYPES = {"json": "application/json", "npy": "application/octet-stream", "png": "image/png",
               "ply": "application/octet-stream"}


def encode(value: Any, fmt: str, *, name: str, index: int | None = None) -> bytes | Any:
    """Encode a state value in ``fmt``; JSON returns a JSON-ready object, the rest bytes."""
    if fmt == "json":
        return to_json(value)
    if fmt == "npy":
        return to_npy(value, name=name, index=index)
    if fmt == "png":
        return to_png(value, name=name, index=index)
    if fmt == "ply":
        return to_ply(value, name=name)
    raise InvalidValue("format", f"unknown format {fmt!r}; formats are {list(FORMATS)}")


def decode_upload(payload: bytes, *, filename: str, content_type: str, annotation: Any, name: str) -> Any:
    """Turn an uploaded file into a state value of type ``annotation``.

    Images accept any image file OpenCV reads (an ImageSet accepts one image, a view appended by
    the caller); arrays and typed values accept JSON or NPY; point clouds accept PLY too.
    """
    import json

    cls = _base_type(annotation)
    suffix = filename.rsplit(".", 1)[-1].lower() if "." in filename else ""
    is_json = suffix == "json" or "json" in (content_type or "")
    is_npy = suffix == "npy" or payload[:6] == b"\x93NUMPY"
    if cls in (Image, ImageSet) and not is_json:
        image = decode_image(payload, name=name)
        return image if cls is Image else ImageSet((Image(image.pixels, name=filename or name),))
    if is_npy:
        array = from_npy(payload, name=name)
        if cls is np.ndarray or cls is None:
            return array
        return decode_json(array.tolist(), cls, name=name)
    if suffix == "ply" and cls in (PointCloud, Mesh, None):
        return from_ply(payload, name=name)
    try:
        data = json.loads(payload.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidValue(name, f"expected JSON, NPY{' or an image file' if cls in (Image, ImageSet) else ''}: {exc}") from None
    return decode_json(data, cls, name=name)
