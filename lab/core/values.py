"""Typed values: what a step returns and what the front ends draw.

A bare array is ambiguous (points or an image?), so every value a user should *see* is one of
these small frozen dataclasses. Each type has exactly one renderer in the viewer
(``lab.viewer.renderers``) and one codec (``lab.core.codecs``); the JSON wire format is derived
from the dataclass fields, so the dataclass is the single source of truth.

Conventions (DESIGN.md section 3): points are float64 ``(N, 2)`` / ``(N, 3)``; images are float32
``(H, W)`` or ``(H, W, 3)`` in [0, 1]; cameras follow OpenCV (x right, y down, z forward,
``X_c = R X_w + t``, pixel (0, 0) is the centre of the top-left pixel).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, is_dataclass
from typing import Literal

import numpy as np

from lab.core.errors import InvalidValue


def _as_array(value: object, *, name: str, dtype: type, shape: tuple[int | None, ...]) -> np.ndarray:
    """Coerce ``value`` to an array of ``dtype`` whose shape matches ``shape`` (None = any)."""
    try:
        array: np.ndarray = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise InvalidValue(name, f"cannot be read as a {np.dtype(dtype).name} array ({exc})") from None
    # zip is strict: the number of dimensions is checked first, so lengths are equal when it runs
    if array.ndim != len(shape) or any(s is not None and s != a
                                       for s, a in zip(shape, array.shape, strict=True)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise InvalidValue(name, f"expected shape {want}, got {tuple(array.shape)}")
    if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return array


def _optional(value: object, *, name: str, dtype: type, shape: tuple[int | None, ...]) -> np.ndarray | None:
    return None if value is None else _as_array(value, name=name, dtype=dtype, shape=shape)


@dataclass(frozen=True, eq=False)
class Image:
    """One image: ``pixels`` is float32 ``(H, W)`` or ``(H, W, 3)`` in [0, 1]."""

    pixels: np.ndarray
    name: str = ""

    def __post_init__(self) -> None:
        pixels = np.asarray(self.pixels)
        if pixels.dtype == np.uint8:
            pixels = pixels.astype(np.float32) / 255.0
        if pixels.ndim == 3 and pixels.shape[2] == 1:
            pixels = pixels[:, :, 0]
        if pixels.ndim not in (2, 3) or (pixels.ndim == 3 and pixels.shape[2] != 3):
            raise InvalidValue("pixels", f"an image is (H, W) or (H, W, 3), got shape {pixels.shape}")
        if pixels.shape[0] < 1 or pixels.shape[1] < 1:
            raise InvalidValue("pixels", "an image needs at least one pixel")
        object.__setattr__(self, "pixels", _as_array(pixels, name="pixels", dtype=np.float32,
                                                     shape=(None,) * pixels.ndim))

    @property
    def height(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def width(self) -> int:
        return int(self.pixels.shape[1])

    def gray(self) -> np.ndarray:
        """``(H, W)`` float32 luminance (ITU-R BT.601 weights, as ``cv2.cvtColor`` RGB2GRAY)."""
        if self.pixels.ndim == 2:
            return self.pixels
        return (self.pixels @ np.array([0.299, 0.587, 0.114], dtype=np.float32)).astype(np.float32)


@dataclass(frozen=True, eq=False)
class ImageSet:
    """An ordered set of views (photos of a board, frames of a sequence, a stereo pair)."""

    images: tuple[Image, ...]

    def __post_init__(self) -> None:
        images = tuple(self.images)
        if not all(isinstance(im, Image) for im in images):
            raise InvalidValue("images", "every entry of an ImageSet must be an Image")
        object.__setattr__(self, "images", images)

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, index: int) -> Image:
        return self.images[index]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(im.name or f"view {i}" for i, im in enumerate(self.images))


@dataclass(frozen=True, eq=False)
class Points2D:
    """2D points on images: ``xy`` float64 ``(N, 2)`` pixels.

    ``view`` (``(N,)`` int) says which view of the image set named ``image`` each point lies on
    (None: all on one image); ``ids`` (``(N,)`` int) names what each point observes (a board
    corner, a 3D point's track). ``colors`` is ``(N, 3)`` float in [0, 1].
    """

    xy: np.ndarray
    view: np.ndarray | None = None
    ids: np.ndarray | None = None
    colors: np.ndarray | None = None
    image: str = "images"

    def __post_init__(self) -> None:
        xy = _as_array(self.xy, name="xy", dtype=np.float64, shape=(None, 2))
        n = len(xy)
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "view", _optional(self.view, name="view", dtype=np.int64, shape=(n,)))
        object.__setattr__(self, "ids", _optional(self.ids, name="ids", dtype=np.int64, shape=(n,)))
        object.__setattr__(self, "colors",
                           _optional(self.colors, name="colors", dtype=np.float64, shape=(n, 3)))

    def __len__(self) -> int:
        return len(self.xy)

    def in_view(self, index: int) -> Points2D:
        """The points on view ``index`` (all of them when ``view`` is None)."""
        if self.view is None:
            return self
        keep = self.view == index
        return Points2D(self.xy[keep], self.view[keep], None if self.ids is None else self.ids[keep],
                        None if self.colors is None else self.colors[keep], self.image)


@dataclass(frozen=True, eq=False)
class PointCloud:
    """3D points ``xyz`` float64 ``(N, 3)`` with optional ``colors`` ``(N, 3)`` in [0, 1]."""

    xyz: np.ndarray
    colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        xyz = _as_array(self.xyz, name="xyz", dtype=np.float64, shape=(None, 3))
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "colors", _optional(self.colors, name="colors", dtype=np.float64,
                                                     shape=(len(xyz), 3)))

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass(frozen=True, eq=False)
class Cameras:
    """``V`` pinhole cameras, OpenCV convention (world to camera ``X_c = R X_w + t``).

    ``K`` ``(V, 3, 3)``, ``R`` ``(V, 3, 3)``, ``t`` ``(V, 3)``, ``dist`` ``(V, 5)`` OpenCV's
    (k1, k2, p1, p2, k3) or None; ``width``/``height`` in pixels; ``image`` names the image set in
    state whose views camera ``i`` carries on its frustum (view ``views[i]``, or view ``i`` when
    ``views`` is None), or "" for none. ``colors`` ``(V, 3)`` tints frustums (e.g. by error).
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    dist: np.ndarray | None = None
    image: str = ""
    views: np.ndarray | None = None
    colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.ndim == 2:
            K = K[None]
        v = len(K)
        R = np.asarray(self.R, dtype=np.float64)
        if R.ndim == 2:
            R = R[None]
        object.__setattr__(self, "K", _as_array(K, name="K", dtype=np.float64, shape=(v, 3, 3)))
        object.__setattr__(self, "R", _as_array(R, name="R", dtype=np.float64, shape=(v, 3, 3)))
        t = np.asarray(self.t, dtype=np.float64).reshape(-1, 3) if np.size(self.t) == 3 * v else self.t
        object.__setattr__(self, "t", _as_array(t, name="t", dtype=np.float64, shape=(v, 3)))
        dist = self.dist
        if dist is not None and np.ndim(dist) == 1:
            dist = np.broadcast_to(np.asarray(dist, dtype=np.float64), (v, len(dist))).copy()
        object.__setattr__(self, "dist", _optional(dist, name="dist", dtype=np.float64, shape=(v, 5)))
        object.__setattr__(self, "views", _optional(self.views, name="views", dtype=np.int64, shape=(v,)))
        object.__setattr__(self, "colors",
                           _optional(self.colors, name="colors", dtype=np.float64, shape=(v, 3)))
        if int(self.width) < 1 or int(self.height) < 1:
            raise InvalidValue("width", "image size must be positive")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def __len__(self) -> int:
        return len(self.K)

    @property
    def centers(self) -> np.ndarray:
        """Camera centres in the world, ``(V, 3)``: ``C = -R^T t``."""
        return -np.einsum("vji,vj->vi", self.R, self.t)


@dataclass(frozen=True, eq=False)
class Segments2D:
    """2D line segments ``start``/``end`` ``(N, 2)`` px, on views as in :class:`Points2D`."""

    start: np.ndarray
    end: np.ndarray
    view: np.ndarray | None = None
    colors: np.ndarray | None = None
    image: str = "images"

    def __post_init__(self) -> None:
        start = _as_array(self.start, name="start", dtype=np.float64, shape=(None, 2))
        n = len(start)
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "end", _as_array(self.end, name="end", dtype=np.float64, shape=(n, 2)))
        object.__setattr__(self, "view", _optional(self.view, name="view", dtype=np.int64, shape=(n,)))
        object.__setattr__(self, "colors",
                           _optional(self.colors, name="colors", dtype=np.float64, shape=(n, 3)))

    def __len__(self) -> int:
        return len(self.start)


@dataclass(frozen=True, eq=False)
class Segments3D:
    """3D line segments ``start``/``end`` ``(N, 3)`` with optional ``colors`` ``(N, 3)``."""

    start: np.ndarray
    end: np.ndarray
    colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        start = _as_array(self.start, name="start", dtype=np.float64, shape=(None, 3))
        n = len(start)
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "end", _as_array(self.end, name="end", dtype=np.float64, shape=(n, 3)))
        object.__setattr__(self, "colors",
                           _optional(self.colors, name="colors", dtype=np.float64, shape=(n, 3)))

    def __len__(self) -> int:
        return len(self.start)


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh: ``vertices`` ``(V, 3)``, ``faces`` ``(F, 3)`` int, ``vertex_colors`` ``(V, 3)``."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        vertices = _as_array(self.vertices, name="vertices", dtype=np.float64, shape=(None, 3))
        faces = _as_array(self.faces, name="faces", dtype=np.int64, shape=(None, 3))
        if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise InvalidValue("faces", "a face index is outside the vertex list")
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "vertex_colors", _optional(self.vertex_colors, name="vertex_colors",
                                                            dtype=np.float64, shape=(len(vertices), 3)))


@dataclass(frozen=True, eq=False)
class GaussianSplats:
    """3D Gaussians: ``centers`` ``(N, 3)``, ``covariances`` ``(N, 3, 3)``, ``rgbs`` ``(N, 3)``,
    ``opacities`` ``(N, 1)``."""

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray

    def __post_init__(self) -> None:
        centers = _as_array(self.centers, name="centers", dtype=np.float64, shape=(None, 3))
        n = len(centers)
        object.__setattr__(self, "centers", centers)
        object.__setattr__(self, "covariances", _as_array(self.covariances, name="covariances",
                                                          dtype=np.float64, shape=(n, 3, 3)))
        object.__setattr__(self, "rgbs", _as_array(self.rgbs, name="rgbs", dtype=np.float64, shape=(n, 3)))
        object.__setattr__(self, "opacities", _as_array(np.reshape(self.opacities, (-1, 1)), name="opacities",
                                                        dtype=np.float64, shape=(n, 1)))


@dataclass(frozen=True, eq=False)
class Curve:
    """Data to plot: one or more series ``y`` ``(S, N)`` over ``x`` ``(N,)``.

    ``kind`` "line" for progress and schedules, "bar" for per-item values (per-view RMS),
    "scatter" for point plots. ``labels`` name the series, ``categories`` the bars.
    """

    x: np.ndarray
    y: np.ndarray
    kind: Literal["line", "bar", "scatter"] = "line"
    title: str = ""
    xlabel: str = ""
    ylabel: str = ""
    labels: tuple[str, ...] = ()
    categories: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        x = _as_array(self.x, name="x", dtype=np.float64, shape=(None,))
        y = np.asarray(self.y, dtype=np.float64)
        if y.ndim == 1:
            y = y[None]
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", _as_array(y, name="y", dtype=np.float64, shape=(None, len(x))))
        if self.kind not in ("line", "bar", "scatter"):
            raise InvalidValue("kind", f"must be line, bar or scatter, got {self.kind!r}")
        object.__setattr__(self, "labels", tuple(self.labels))
        object.__setattr__(self, "categories", tuple(self.categories))


#: Every drawable value type, by name (the ``"type"`` tag of the JSON codec).
VALUE_TYPES: dict[str, type] = {
    cls.__name__: cls
    for cls in (Image, ImageSet, Points2D, PointCloud, Cameras, Segments2D, Segments3D, Mesh,
                GaussianSplats, Curve)
}


def value_nbytes(value: object) -> int:
    """Approximate memory held by a state value (arrays only), for the session store's cap."""
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    if isinstance(value, (list, tuple)):
        return sum(value_nbytes(v) for v in value)
    if isinstance(value, dict):
        return sum(value_nbytes(v) for v in value.values())
    if is_dataclass(value):
        return sum(value_nbytes(getattr(value, f.name)) for f in fields(value))
    return 64


__all__ = ["VALUE_TYPES", "Cameras", "Curve", "GaussianSplats", "Image", "ImageSet", "Mesh", "PointCloud",
           "Points2D", "Segments2D", "Segments3D", "field", "value_nbytes"]
