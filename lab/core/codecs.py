"""Codecs for state values: JSON, NPY, PNG and PLY out; JSON, NPY and image files in.

The JSON form of a typed value is derived from its dataclass fields (viser's lesson: one
dataclass is the single source of truth for the wire format): ``{"type": "Points2D", "xy":
[[...]], ...}``; arrays become nested lists. ``decode_json`` reverses it for uploads.
"""

from __future__ import annotations

import dataclasses
import io
import re
import struct
import typing
from typing import Any, BinaryIO

import numpy as np

from lab.core import budgets
from lab.core.errors import InvalidValue
from lab.core.values import VALUE_TYPES, Cameras, Curve, Image, ImageSet, Mesh, PointCloud, Points2D

FORMATS = ("json", "npy", "png", "ply")


# --- JSON ---------------------------------------------------------------------------------------
def to_json(value: Any) -> Any:
    """A JSON-ready form of any state value."""
    if isinstance(value, np.ndarray):
        if value.dtype.kind == "b":
            return value.tolist()
        if value.dtype.kind == "f":
            return np.where(np.isfinite(value), value, np.array(None)).tolist()
        return value.tolist()
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


def json_numbers(value: Any) -> int:
    """How many numbers (array entries and scalars) :func:`to_json` writes for ``value``, without
    building it."""
    if isinstance(value, np.ndarray):
        return int(value.size)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return sum(json_numbers(getattr(value, f.name)) for f in dataclasses.fields(value))
    if isinstance(value, dict):
        return sum(json_numbers(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(json_numbers(v) for v in value)
    return 1 if isinstance(value, (int, float, np.number, np.bool_)) else 0


def check_json_answer(value: Any, *, name: str) -> None:
    """Refuse (InvalidValue on ``format``) a value whose JSON would hold over
    :data:`lab.core.budgets.MAX_JSON_NUMBERS` numbers, pointing to the binary formats that carry it at
    its own size."""
    count = json_numbers(value)
    if count > budgets.MAX_JSON_NUMBERS:
        binary = "format=npy or format=png" if isinstance(value, (Image, ImageSet)) else "format=npy"
        raise InvalidValue("format", f"{name!r} holds {count} numbers, too many for format=json (at most "
                                     f"{budgets.MAX_JSON_NUMBERS}, lab.core.budgets.MAX_JSON_NUMBERS): "
                                     f"read it as {binary}, or one part of it with ?index=N")


_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"')
_JSON_CHUNK = 2**20


def json_depth(payload: bytes) -> int:
    """The deepest nesting of arrays and objects in the JSON text ``payload`` (brackets inside strings
    ignored).

    Counted without parsing (Python's ``json`` recurses once per level), in chunks of a MiB.
    """
    codes = np.frombuffer(_JSON_STRING.sub(b"", payload), dtype=np.uint8)
    depth, deepest = 0, 0
    for start in range(0, len(codes), _JSON_CHUNK):
        chunk = codes[start:start + _JSON_CHUNK]
        opened = (chunk == ord("[")).astype(np.int64) + (chunk == ord("{"))
        steps = opened - (chunk == ord("]")) - (chunk == ord("}"))
        if len(steps):
            levels = np.cumsum(steps) + depth
            deepest = max(deepest, int(levels.max()))
            depth = int(levels[-1])
    return deepest


def check_json_depth(payload: bytes, *, name: str) -> None:
    """Refuse (InvalidValue on ``name``) JSON nested deeper than :data:`lab.core.budgets.MAX_JSON_DEPTH`."""
    depth = json_depth(payload)
    if depth > budgets.MAX_JSON_DEPTH:
        raise InvalidValue(name, f"the JSON nests {depth} levels of arrays and objects; at most "
                                 f"{budgets.MAX_JSON_DEPTH} are accepted (lab.core.budgets.MAX_JSON_DEPTH)")


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
                raise InvalidValue(name, f"{cls.__name__} has no field(s) {sorted(unknown)}; "
                                         f"fields are {sorted(known)}")
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
                raise InvalidValue("index", f"{name!r} holds images of different sizes: "
                                            "ask for one with ?index=")
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
        raise InvalidValue("index", f"{name!r} has {len(images)} views; "
                                    f"index must be in [0, {len(images) - 1}]")
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
        raise InvalidValue(name, "a .npy upload must hold a numeric array, "
                                 f"got dtype {getattr(array, 'dtype', '?')}")
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


#: The image files whose size :func:`image_size` reads from the header (the others are refused).
HEADER_FORMATS = "PNG, JPEG, JPEG 2000, TIFF, BMP, WebP, GIF, PNM/PAM/PFM, Sun raster or Radiance HDR"


def image_size(stream: BinaryIO) -> tuple[int, int] | None:
    """``(width, height)`` of the image file open in ``stream``, read from its header; None when unknown.

    Nothing is decoded: PNG's IHDR, JPEG's start-of-frame, TIFF's first IFD (the page OpenCV
    reads), BMP's DIB header, WebP's VP8/VP8L/VP8X chunk, GIF's logical screen, JPEG 2000's SIZ
    marker or ``ihdr`` box, the text headers of PNM/PAM/PFM and Radiance HDR, Sun raster's header.
    The stream is read from its start; OpenEXR and unknown files give None.
    """
    stream.seek(0)
    head = stream.read(32)
    try:
        if head.startswith(b"\x89PNG\r\n\x1a\n") and head[12:16] == b"IHDR":
            return struct.unpack(">II", head[16:24])
        if head.startswith(b"\xff\xd8"):
            return _jpeg_size(stream)
        if head[:4] in (b"II*\x00", b"MM\x00*"):
            return _tiff_size(stream, "<" if head[:2] == b"II" else ">")
        if head.startswith(b"BM"):
            header_size = struct.unpack("<I", head[14:18])[0]
            if header_size == 12:
                return struct.unpack("<HH", head[18:22])
            width, height = struct.unpack("<ii", head[18:26])
            return abs(width), abs(height)
        if head.startswith(b"RIFF") and head[8:12] == b"WEBP":
            return _webp_size(head + stream.read(8))
        if head[:6] in (b"GIF87a", b"GIF89a"):
            return struct.unpack("<HH", head[6:10])
        if head.startswith(b"\x59\xa6\x6a\x95"):
            return struct.unpack(">ii", head[4:12])
        if head[:1] == b"P" and head[1:2] in b"1234567fF" and head[1:2]:
            return _netpbm_size(head + stream.read(4096))
        if head.startswith((b"#?RADIANCE", b"#?RGBE")):
            return _radiance_size(head + stream.read(65536))
        if head.startswith(b"\xff\x4f\xff\x51"):  # a JPEG 2000 codestream: SIZ follows SOC
            x, y, x0, y0 = struct.unpack(">IIII", head[8:24])
            return x - x0, y - y0
        if head[4:12] == b"jP  \r\n\x87\n":
            return _jp2_size(stream)
    except struct.error:  # a header cut short
        return None
    return None


def _jpeg_size(stream: BinaryIO) -> tuple[int, int] | None:
    """Walk JPEG's marker segments to the first start-of-frame (SOF0..SOF15 but DHT, JPG, DAC).

    At most 4096 segments are walked (a real file reaches its frame header within a few dozen).
    """
    stream.seek(2)
    for _ in range(4096):
        byte = stream.read(1)
        if byte != b"\xff":  # each segment starts with a marker
            return None
        for _ in range(64):  # fill bytes before the marker's code
            byte = stream.read(1)
            if byte != b"\xff":
                break
        if not byte or byte == b"\xff":
            return None
        marker = byte[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # segments without a length
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header before them
            return None
        length = struct.unpack(">H", stream.read(2))[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            height, width = struct.unpack(">xHH", stream.read(5))
            return (width, height) if width and height else None
        if length < 2:
            return None
        stream.seek(length - 2, io.SEEK_CUR)
    return None


def _jp2_size(stream: BinaryIO) -> tuple[int, int] | None:
    """The image header box (``ihdr``: height, width) inside a JP2 file's ``jp2h`` box."""
    stream.seek(0)
    end = None
    while end is None or stream.tell() < end:
        start = stream.tell()
        length, kind = struct.unpack(">I4s", stream.read(8))
        if length == 1:
            length = struct.unpack(">Q", stream.read(8))[0]
        if kind == b"jp2h":  # a super box: walk its children
            end = start + length
            continue
        if kind == b"ihdr":
            height, width = struct.unpack(">II", stream.read(8))
            return width, height
        if length < 8:
            return None
        stream.seek(start + length)
    return None


def _tiff_size(stream: BinaryIO, order: str) -> tuple[int, int] | None:
    """ImageWidth (256) and ImageLength (257) of a TIFF's first image file directory."""
    stream.seek(4)
    (offset,) = struct.unpack(order + "I", stream.read(4))
    stream.seek(offset)
    (count,) = struct.unpack(order + "H", stream.read(2))
    found: dict[int, int] = {}
    for _ in range(min(count, 4096)):
        tag, kind, _n, value = struct.unpack(order + "HHI4s", stream.read(12))
        if tag in (256, 257):
            found[tag] = struct.unpack(order + ("H" if kind == 3 else "I"), value[:2 if kind == 3 else 4])[0]
    return (found[256], found[257]) if len(found) == 2 else None


def _webp_size(head: bytes) -> tuple[int, int] | None:
    chunk = head[12:16]
    if chunk == b"VP8 ":
        width, height = struct.unpack("<HH", head[26:30])
        return width & 0x3FFF, height & 0x3FFF
    if chunk == b"VP8L":
        (bits,) = struct.unpack("<I", head[21:25])
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b"VP8X":
        return (int.from_bytes(head[24:27], "little") + 1, int.from_bytes(head[27:30], "little") + 1)
    return None


def _netpbm_size(head: bytes) -> tuple[int, int] | None:
    """PBM/PGM/PPM (P1-P6) and PFM (PF, Pf): magic, width, height; PAM (P7): WIDTH and HEIGHT lines."""
    text = re.sub(rb"#[^\n]*", b" ", head)
    if head[1:2] == b"7":
        width, height = re.search(rb"\bWIDTH\s+(\d+)", text), re.search(rb"\bHEIGHT\s+(\d+)", text)
        return (int(width.group(1)), int(height.group(1))) if width and height else None
    fields = re.match(rb"P[1-6fF]\s+(\d+)\s+(\d+)", text)
    return (int(fields.group(1)), int(fields.group(2))) if fields else None


def _radiance_size(head: bytes) -> tuple[int, int] | None:
    """The resolution line after Radiance's header (``-Y height +X width`` or a transposed order)."""
    found = re.search(rb"\n\n([-+])([XY]) (\d+) ([-+])([XY]) (\d+)\n", head)
    if not found:
        return None
    first, second = int(found.group(3)), int(found.group(6))
    return (second, first) if found.group(2) == b"Y" else (first, second)


def check_image_header(stream: BinaryIO, *, field: str, what: str) -> tuple[int, int]:
    """The size of the image in ``stream`` after checking it against
    :data:`lab.core.budgets.MAX_IMAGE_PIXELS`.

    Raises InvalidValue when the header gives no size (not an image file the lab reads),
    CapacityExceeded when the image is too large; both before any pixel is decoded.
    """
    size = image_size(stream)
    if size is None or size[0] <= 0 or size[1] <= 0:
        raise InvalidValue(field, f"cannot read {what}: not an image file the lab reads ({HEADER_FORMATS})")
    budgets.check_image_pixels(*size, field=field, what=what)
    return size


def decode_image(payload: bytes, *, name: str, what: str = "the upload") -> Image:
    """An uploaded image file as an :class:`Image` (RGB float32 in [0, 1]), refused from its header
    when too large.

    ``what`` names the file in errors (``"'left.png'"``); the field at fault is ``name``.
    """
    import cv2

    check_image_header(io.BytesIO(payload), field=name, what=what)
    decoded = cv2.imdecode(np.frombuffer(payload, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if decoded is None:
        raise InvalidValue(name, f"{what} is not an image file OpenCV can read ({HEADER_FORMATS})")
    return image_from_cv2(decoded, name=name)


def image_from_cv2(decoded: np.ndarray, *, name: str = "") -> Image:
    """Convert an array from ``cv2.imread``/``imdecode`` (BGR or BGRA, any depth) to an :class:`Image`.

    One float32 copy is made (channels reordered while converting), then scaled and clipped in
    place, so a large photo costs its float pixels and not three times them.
    """
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(decoded.dtype, 1.0)
    if decoded.ndim == 3 and decoded.shape[2] in (3, 4):
        decoded = decoded[:, :, 2::-1]  # BGR(A) -> RGB, alpha dropped: a view, copied once below
    pixels = np.ascontiguousarray(decoded, dtype=np.float32)
    if pixels is decoded:  # already float32 and contiguous: do not scale the caller's array
        pixels = pixels.copy()
    if scale != 1.0:
        np.divide(pixels, np.float32(scale), out=pixels)
    np.clip(pixels, 0.0, 1.0, out=pixels)
    return Image(pixels, name=name)


# --- PLY ----------------------------------------------------------------------------------------
def to_ply(value: Any, *, name: str) -> bytes:
    """Binary PLY of a point cloud (with colours) or a mesh, through trimesh."""
    import trimesh

    geometry: trimesh.PointCloud | trimesh.Trimesh
    if isinstance(value, PointCloud):
        colors = None if value.colors is None else _colour_bytes(value.colors)
        geometry = trimesh.PointCloud(value.xyz, colors=colors)
    elif isinstance(value, Mesh):
        colors = None if value.vertex_colors is None else _colour_bytes(value.vertex_colors)
        geometry = trimesh.Trimesh(value.vertices, value.faces, vertex_colors=colors, process=False)
    elif isinstance(value, np.ndarray) and value.ndim == 2 and value.shape[1] == 3:
        geometry = trimesh.PointCloud(value)
    else:
        raise InvalidValue("format", f"{name!r} ({type(value).__name__}) is not a point cloud or mesh; "
                                     "use format=json")
    return typing.cast(bytes, geometry.export(file_type="ply"))  # a binary PLY: trimesh gives bytes


def _colour_bytes(colours: np.ndarray) -> np.ndarray:
    """Colours in [0, 1] as PLY's uint8 (rounded, clipped)."""
    return np.clip(colours * 255 + 0.5, 0, 255).astype(np.uint8)


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
    cloud = typing.cast("trimesh.PointCloud", loaded)  # a PLY without faces loads as a point cloud
    colors = getattr(cloud, "colors", None)
    colors = None if colors is None or len(colors) == 0 else np.asarray(colors)[:, :3] / 255.0
    return PointCloud(np.asarray(cloud.vertices), colors)


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
        image = decode_image(payload, name=name, what=repr(filename) if filename else "the upload")
        return image if cls is Image else ImageSet((Image(image.pixels, name=filename or name),))
    if is_npy:
        array = from_npy(payload, name=name)
        if cls is np.ndarray or cls is None:
            return array
        return decode_json(array.tolist(), cls, name=name)
    if suffix == "ply" and cls in (PointCloud, Mesh, None):
        return from_ply(payload, name=name)
    check_json_depth(payload, name=name)
    try:
        data = json.loads(payload.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        images = " or an image file" if cls in (Image, ImageSet) else ""
        raise InvalidValue(name, f"expected JSON, NPY{images}: {exc}") from None
    return decode_json(data, cls, name=name)
