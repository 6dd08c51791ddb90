"""What a synthetic scene is made of: textured planes, boxes, spheres and triangle meshes.

Every object answers three questions for the ray caster of :mod:`lab.data.scenes.render`:

- ``hull()``: the corners and edges of a convex polytope that encloses it (for culling: its
  projection bounds the pixels the object can cover);
- ``intersect(origin, directions)``: for rays ``X(s) = origin + s d`` sharing one origin (the camera
  centre) with directions ``d`` ``(N, 3)``, the parameter ``s`` of the nearest hit beyond ``NEAR``
  (``inf`` for a miss) and an integer per ray (the face hit, or -1). The ray caster scales ``d`` so
  that its camera-frame z is 1, so ``s`` is the depth Z of the hit;
- ``surface(points, aux)``: at hit points ``(M, 3)``, the outward normal and the albedo, through a
  :class:`~lab.data.scenes.textures.Texture` lookup whose footprint the caller supplies.

Intersections are the closed forms of a ray-tracing course (P. Shirley and R. K. Morley,
*Realistic Ray Tracing*, 2nd ed., 2003, chapter 3: ray-plane, ray-sphere, the slab test for
boxes (Kay and Kajiya 1986)); triangle meshes use Embree through ``trimesh.ray.ray_pyembree``
when ``embreex`` is installed and otherwise the Moeller-Trumbore test written here (T. Moeller
and B. Trumbore, "Fast, minimum storage ray-triangle intersection", JGT 2(1), 1997), batched.
Either way the distance is then recomputed in float64 from the triangle's plane, so depth is
exact whatever precision the search used.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, NamedTuple, TypedDict, Unpack

import numpy as np
from numpy.typing import ArrayLike

from lab.core.errors import InvalidValue
from lab.data.scenes.textures import Texture, as_texture

if TYPE_CHECKING:  # trimesh is imported when a mesh is made: scenes without one never load it
    import trimesh
    from _typeshed import DataclassInstance

#: Hits closer than this (metres along the camera's z axis) are ignored: the near clipping plane.
NEAR = 1e-3

#: Edges of a box whose corners are numbered by bits (x, y, z) = (k & 1, k >> 1 & 1, k >> 2 & 1).
_BOX_EDGES = np.array([(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6),
                       (3, 7)])
_BOX_SIGNS = np.array([[(k & 1) * 2 - 1, (k >> 1 & 1) * 2 - 1, (k >> 2 & 1) * 2 - 1] for k in range(8)],
                      float)


class Surface(NamedTuple):
    """What a hit point looks like: ``normal`` ``(M, 3)`` unit, outward; then either ``uv`` ``(M, 2)``
    texture coordinates with ``density`` (texture tiles per metre, scalar or ``(M,)``), or ``color``
    ``(M, 3)`` when the object has no texture."""

    normal: np.ndarray
    uv: np.ndarray | None = None
    density: np.ndarray | float = 1.0
    color: np.ndarray | None = None


# --- checks -------------------------------------------------------------------------------------------
def _vector(value: object, name: str, size: int = 3) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InvalidValue(name, f"expected {size} numbers, got {value!r}") from None
    if array.shape != (size,) or not np.all(np.isfinite(array)):
        raise InvalidValue(name, f"expected {size} finite numbers, got {value!r}")
    return array


def _unit(value: object, name: str) -> np.ndarray:
    vector = _vector(value, name)
    norm = np.linalg.norm(vector)
    if norm < 1e-12:
        raise InvalidValue(name, "must be a non-zero vector")
    return vector / norm


def _positive(value: object, name: str, size: int) -> np.ndarray:
    array = _vector(value, name, size)
    if np.any(array <= 0):
        raise InvalidValue(name, f"must be positive, got {value!r}")
    return array


def _color(value: object, name: str = "color") -> np.ndarray:
    rgb = _vector(value, name)
    if np.any(rgb < 0) or np.any(rgb > 1):
        raise InvalidValue(name, f"an RGB colour has components in [0, 1], got {value!r}")
    return rgb


def _rotation(value: object, name: str = "rotation") -> np.ndarray:
    R = np.eye(3) if value is None else np.asarray(value, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9) \
            or np.linalg.det(R) < 0:
        raise InvalidValue(name, "expected a (3, 3) rotation matrix (orthonormal, determinant +1)")
    return R


def _readonly(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=np.float64)
    array.setflags(write=False)
    return array


def _uniform(color: tuple[float, float, float], shape: tuple[int, ...]) -> np.ndarray:
    """``color`` at every point: a float32 broadcast of ``shape`` (the albedo of an untextured object)."""
    return np.broadcast_to(np.asarray(color, dtype=np.float32), shape)


def _floats(values: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


def _set_fields(instance: DataclassInstance, **values: object) -> None:
    """Set every field of the frozen dataclass ``instance``, in field order (what a generated
    ``__init__`` does; the scene objects write their own, which check and convert their inputs)."""
    for f in fields(instance):
        object.__setattr__(instance, f.name, values[f.name])


# --- shared ray math ------------------------------------------------------------------------------------
def slab(origin: np.ndarray, directions: np.ndarray, lower: np.ndarray,
         upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The slab test (Kay and Kajiya 1986): entry and exit parameters ``(N,)`` of rays in an
    axis-aligned box.

    A ray misses when ``entry > exit`` or ``exit < NEAR``. Axis-parallel rays give infinite slab
    bounds, which the NaN-ignoring reductions (``np.fmax``/``np.fmin``) handle.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / directions
        near_side = (lower - origin) * inverse
        far_side = (upper - origin) * inverse
    low = np.minimum(near_side, far_side)
    high = np.maximum(near_side, far_side)
    entry = np.fmax(np.fmax(low[:, 0], low[:, 1]), low[:, 2])
    exit_ = np.fmin(np.fmin(high[:, 0], high[:, 1]), high[:, 2])
    return entry, exit_


def _first_beyond_near(entry: np.ndarray, exit_: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """The nearest parameter beyond NEAR of an interval ``[entry, exit]`` (the exit when the origin is
    inside)."""
    s = np.where(entry >= NEAR, entry, exit_)
    return np.where(hit & (s >= NEAR), s, np.inf)


def _box_hull(center: np.ndarray, axes: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners ``(8, 3)`` and edges ``(12, 2)`` of an oriented box; ``axes`` has the box axes as columns."""
    return center + (_BOX_SIGNS * half) @ axes.T, _BOX_EDGES


# --- planes -----------------------------------------------------------------------------------------------
class PlaneOptions(TypedDict, total=False):
    """The keyword options of :class:`Plane` (for :meth:`Plane.centered`)."""

    texture: Texture | np.ndarray | None
    color: tuple[float, float, float]
    repeat: tuple[float, float]
    name: str


@dataclass(frozen=True, eq=False, init=False)
class Plane:
    """A textured rectangle: the points ``origin + a u_axis + b v_axis``, ``0 <= a <= size[0]``,
    ``0 <= b <= size[1]``.

    ``u_axis`` and ``v_axis`` are perpendicular directions (normalized here); the texture's
    ``(u, v) = (repeat[0] a / size[0], repeat[1] b / size[1])``, so texel row 0 lies along
    ``origin + a u_axis`` and the texture tiles ``repeat`` times. Without a texture the plane is
    ``color``. Both sides are visible.
    """

    # what the constructor stores (it takes any array-like vectors and an image for the texture)
    origin: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray
    size: tuple[float, float]
    texture: Texture | None
    color: tuple[float, float, float]
    repeat: tuple[float, float]
    name: str

    def __init__(self, origin: ArrayLike, u_axis: ArrayLike, v_axis: ArrayLike, size: tuple[float, float],
                 texture: Texture | np.ndarray | None = None,
                 color: tuple[float, float, float] = (0.6, 0.6, 0.6),
                 repeat: tuple[float, float] = (1.0, 1.0), name: str = "plane") -> None:
        u = _unit(u_axis, "u_axis")
        v = _unit(v_axis, "v_axis")
        if abs(float(u @ v)) > 1e-9:
            raise InvalidValue("v_axis", "the two axes of a plane must be perpendicular")
        _set_fields(self, origin=_readonly(_vector(origin, "origin")), u_axis=_readonly(u),
                    v_axis=_readonly(v), size=_floats(_positive(size, "size", 2)),
                    repeat=_floats(_positive(repeat, "repeat", 2)), texture=as_texture(texture),
                    color=_floats(_color(color)), name=name)

    @classmethod
    def centered(cls, center: object, u_axis: object, v_axis: object, size: tuple[float, float],
                 **options: Unpack[PlaneOptions]) -> Plane:
        """The rectangle of ``size`` centred on ``center`` (same options as the constructor)."""
        u, v = _unit(u_axis, "u_axis"), _unit(v_axis, "v_axis")
        w, h = _positive(size, "size", 2)
        return cls(_vector(center, "center") - 0.5 * w * u - 0.5 * h * v, u, v, (w, h), **options)

    @property
    def normal(self) -> np.ndarray:
        """``u_axis x v_axis``, ``(3,)``."""
        return np.cross(self.u_axis, self.v_axis)

    def point(self, a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
        """World points at plane coordinates ``(a, b)`` (metres along the two axes): ``(..., 3)``."""
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        return self.origin + a[..., None] * self.u_axis + b[..., None] * self.v_axis

    def hull(self) -> tuple[np.ndarray, np.ndarray]:
        corners = self.point(np.array([0.0, self.size[0], self.size[0], 0.0]),
                             np.array([0.0, 0.0, self.size[1], self.size[1]]))
        return corners, np.array([(0, 1), (1, 2), (2, 3), (3, 0)])

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, None]:
        """Ray-plane: ``s = n . (o_plane - o) / n . d``, kept where the hit lies inside the rectangle."""
        frame = np.stack([self.normal, self.u_axis, self.v_axis], axis=1)  # (3, 3): columns n, u, v
        along = directions @ frame
        offset = self.origin - origin
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (self.normal @ offset) / along[:, 0]
        a = s * along[:, 1] - self.u_axis @ offset
        b = s * along[:, 2] - self.v_axis @ offset
        inside = (s >= NEAR) & (a >= 0) & (a <= self.size[0]) & (b >= 0) & (b <= self.size[1])
        return np.where(inside, s, np.inf), None

    def surface(self, points: np.ndarray, aux: np.ndarray) -> Surface:
        normal = np.broadcast_to(self.normal, points.shape)
        if self.texture is None:
            return Surface(normal, color=_uniform(self.color, points.shape))
        relative = points - self.origin
        uv = np.stack([relative @ self.u_axis * (self.repeat[0] / self.size[0]),
                       relative @ self.v_axis * (self.repeat[1] / self.size[1])], axis=1)
        density = max(self.repeat[0] / self.size[0], self.repeat[1] / self.size[1])
        return Surface(normal, uv, density)


# --- boxes ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Box:
    """A textured box: ``center``, edge lengths ``size`` along its axes, ``rotation`` (box axes as
    columns; None: the world axes).

    A world point is ``center + rotation @ p`` for ``p`` in ``[-size/2, size/2]``. The texture is
    an atlas of 3 x 2 cells (:func:`~lab.data.scenes.textures.atlas`), one per face in the order
    +x, -x, +y, -y (first row), +z, -z (second row); on a side face the cell's rows run down the
    box's z axis. Without a texture the box is ``color``.
    """

    # what the constructor stores (it takes an array-like centre, no rotation, an image for the texture)
    center: np.ndarray
    size: tuple[float, float, float]
    rotation: np.ndarray
    texture: Texture | None
    color: tuple[float, float, float]
    name: str

    def __init__(self, center: ArrayLike, size: tuple[float, float, float],
                 rotation: np.ndarray | None = None, texture: Texture | np.ndarray | None = None,
                 color: tuple[float, float, float] = (0.6, 0.6, 0.6), name: str = "box") -> None:
        _set_fields(self, center=_readonly(_vector(center, "center")),
                    size=_floats(_positive(size, "size", 3)), rotation=_readonly(_rotation(rotation)),
                    texture=as_texture(texture), color=_floats(_color(color)), name=name)

    def hull(self) -> tuple[np.ndarray, np.ndarray]:
        return _box_hull(self.center, self.rotation, 0.5 * np.asarray(self.size))

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, None]:
        """The slab test in the box's frame (rays rotated by ``rotation^T``)."""
        half = 0.5 * np.asarray(self.size)
        local_origin = (origin - self.center) @ self.rotation
        entry, exit_ = slab(local_origin, directions @ self.rotation, -half, half)
        return _first_beyond_near(entry, exit_, entry <= exit_), None

    def surface(self, points: np.ndarray, aux: np.ndarray) -> Surface:
        half = 0.5 * np.asarray(self.size)
        local = (points - self.center) @ self.rotation
        scaled = local / half
        axis = np.argmax(np.abs(scaled), axis=1)
        positive = scaled[np.arange(len(points)), axis] > 0
        face = 2 * axis + (~positive)
        normal = (self.rotation[:, axis] * np.where(positive, 1.0, -1.0)).T
        if self.texture is None:
            return Surface(normal, color=_uniform(self.color, points.shape))
        # in-face coordinates in [0, 1]: side faces (x, y) run (other horizontal axis, down z);
        # top/bottom (x, y)
        first = np.where(axis == 0, 1, 0)
        second = np.where(axis == 2, 1, 2)
        rows = np.arange(len(points))
        a = 0.5 * (scaled[rows, first] + 1.0)
        b = 0.5 * (scaled[rows, second] + 1.0)
        b = np.where(axis == 2, b, 1.0 - b)
        a = np.where(positive, a, 1.0 - a)
        column, row = face % 3, face // 3
        eps = 1e-4  # stay inside the cell, so that bilinear filtering does not bleed into its neighbour
        uv = np.stack([(column + np.clip(a, eps, 1 - eps)) / 3.0, (row + np.clip(b, eps, 1 - eps)) / 2.0],
                      axis=1)
        extent = np.array([half[first] * 2.0, half[second] * 2.0])  # (2, M) face edge lengths
        density = np.maximum(1.0 / (3.0 * extent[0]), 1.0 / (2.0 * extent[1]))
        return Surface(normal, uv, density)


# --- spheres ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Sphere:
    """A textured sphere of ``radius`` about ``center``.

    The texture is wrapped equirectangularly in the frame ``rotation`` (columns: the frame's axes):
    ``u = longitude / 2 pi + 1/2`` about its z axis, ``v = colatitude / pi`` from its +z pole,
    tiled ``repeat`` times.
    """

    # what the constructor stores (it takes an array-like centre, no rotation, an image for the texture)
    center: np.ndarray
    radius: float
    texture: Texture | None
    color: tuple[float, float, float]
    rotation: np.ndarray
    repeat: tuple[float, float]
    name: str

    def __init__(self, center: ArrayLike, radius: float, texture: Texture | np.ndarray | None = None,
                 color: tuple[float, float, float] = (0.6, 0.6, 0.6), rotation: np.ndarray | None = None,
                 repeat: tuple[float, float] = (1.0, 1.0), name: str = "sphere") -> None:
        checked = {"center": _readonly(_vector(center, "center")),  # checked in this order
                   "radius": float(_positive(radius, "radius", 1)[0]),
                   "rotation": _readonly(_rotation(rotation)),
                   "repeat": _floats(_positive(repeat, "repeat", 2))}
        _set_fields(self, texture=as_texture(texture), color=_floats(_color(color)), name=name, **checked)

    def hull(self) -> tuple[np.ndarray, np.ndarray]:
        return _box_hull(self.center, np.eye(3), np.full(3, self.radius))

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, None]:
        """Ray-sphere: the smaller root of ``|o + s d - c|^2 = r^2`` beyond NEAR (the larger one from
        inside).

        Solved as ``s = c' / q`` and ``q / a`` with ``q = -(b' + sign(b') sqrt(disc))`` (Numerical
        Recipes, section 5.6), which loses no digits to cancellation.
        """
        offset = origin - self.center
        a = np.einsum("ij,ij->i", directions, directions)
        half_b = directions @ offset
        c = offset @ offset - self.radius ** 2
        disc = half_b * half_b - a * c
        hit = disc >= 0
        root = np.sqrt(np.where(hit, disc, 0.0))
        q = -(half_b + np.copysign(root, half_b))
        with np.errstate(divide="ignore", invalid="ignore"):
            s1, s2 = q / a, c / q
        return _first_beyond_near(np.fmin(s1, s2), np.fmax(s1, s2), hit), None

    def surface(self, points: np.ndarray, aux: np.ndarray) -> Surface:
        normal = (points - self.center) / self.radius
        if self.texture is None:
            return Surface(normal, color=_uniform(self.color, points.shape))
        local = normal @ self.rotation
        u = np.arctan2(local[:, 1], local[:, 0]) / (2 * np.pi) + 0.5
        colatitude = np.arccos(np.clip(local[:, 2], -1.0, 1.0))
        uv = np.stack([self.repeat[0] * u, self.repeat[1] * colatitude / np.pi], axis=1)
        around = self.repeat[0] / (2 * np.pi * self.radius * np.maximum(np.sin(colatitude), 0.05))
        density = np.maximum(around, self.repeat[1] / (np.pi * self.radius))
        return Surface(normal, uv, density)


# --- triangle meshes --------------------------------------------------------------------------------------
def moller_trumbore(origin: np.ndarray, directions: np.ndarray, triangles: np.ndarray, *,
                    chunk_elements: int = 2_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of rays ``origin + s d`` (``d`` ``(N, 3)``) with triangles ``(F, 3, 3)``: ``s``,
    face ``(N,)``.

    The Moeller-Trumbore test (1997) for every ray against every triangle, in chunks of about
    ``chunk_elements`` ray-triangle pairs; both sides of a triangle count, misses are ``inf`` / -1.
    What ``trimesh.ray.ray_triangle.RayMeshIntersector.intersects_first`` computes (it culls with an
    R-tree first, which this does not: meant for small meshes and for checking Embree).
    """
    n = len(directions)
    best_s = np.full(n, np.inf)
    best_face = np.full(n, -1, dtype=np.int64)
    if n == 0 or len(triangles) == 0:
        return best_s, best_face
    v0 = triangles[:, 0]
    e1 = triangles[:, 1] - v0
    e2 = triangles[:, 2] - v0
    t_vec = origin - v0  # (F, 3): the ray origin is shared
    q = np.cross(t_vec, e1)  # (F, 3)
    s_num = np.einsum("fj,fj->f", q, e2)  # q . e2
    step = max(1, chunk_elements // len(triangles))
    for start in range(0, n, step):
        d = directions[start:start + step]
        p = np.cross(d[:, None, :], e2[None])  # (n, F, 3)
        det = np.einsum("nfj,fj->nf", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            u = np.einsum("nfj,fj->nf", p, t_vec) * inv
            v = (d @ q.T) * inv
            s = s_num[None] * inv
        valid = (np.abs(det) > 1e-300) & (u >= 0) & (v >= 0) & (u + v <= 1) & (s >= NEAR)
        s = np.where(valid, s, np.inf)
        face = np.argmin(s, axis=1)
        best_s[start:start + step] = s[np.arange(len(d)), face]
        best_face[start:start + step] = np.where(np.isfinite(best_s[start:start + step]), face, -1)
    return best_s, best_face


def binned_moller_trumbore(origin: np.ndarray, directions: np.ndarray, triangles: np.ndarray, *,
                           cells: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """:func:`moller_trumbore` with culling: rays and triangles binned on a grid of their central projection.

    All rays share ``origin``, so each ray is a point and each triangle a bounded region of the
    plane they are projected on (perpendicular to the mean direction, at distance 1): a ray can
    only hit triangles whose projected bounding box contains it. Rays are binned in a
    ``cells x cells`` grid over their bounding box, triangles into every cell their box overlaps,
    and each cell is tested by :func:`moller_trumbore` alone. Triangles reaching behind the
    origin's plane have no bounded projection and are tested in every cell. Same result as
    :func:`moller_trumbore` (a ray-triangle test is the same per pair); a uniform grid stands in
    for the bounding volume hierarchy of Embree or trimesh's R-tree.
    """
    n = len(directions)
    if n == 0 or len(triangles) == 0:
        return np.full(n, np.inf), np.full(n, -1, dtype=np.int64)
    mean = directions.mean(axis=0)
    axis = mean / max(np.linalg.norm(mean), 1e-300)
    along = directions @ axis
    if np.linalg.norm(mean) < 1e-12 or along.min() <= 1e-9 * np.abs(directions).max():
        return moller_trumbore(origin, directions, triangles)  # rays spread over a half-space: no projection
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    ray_x, ray_y = directions @ e1 / along, directions @ e2 / along
    relative = triangles - origin
    depth = relative @ axis  # (F, 3)
    bounded = np.all(depth > 1e-12, axis=1)
    safe = np.where(bounded[:, None], depth, 1.0)
    tri_x, tri_y = relative @ e1 / safe, relative @ e2 / safe
    x0, x1, y0, y1 = ray_x.min(), ray_x.max(), ray_y.min(), ray_y.max()
    scale_x = cells / max(x1 - x0, 1e-300)
    scale_y = cells / max(y1 - y0, 1e-300)
    def to_cell(value: np.ndarray, low: float, scale: float) -> np.ndarray:
        return np.clip(np.floor((value - low) * scale), 0, cells - 1).astype(np.int64)

    ray_cell = to_cell(ray_x, x0, scale_x) * cells + to_cell(ray_y, y0, scale_y)
    lo_x, hi_x = np.where(bounded, tri_x.min(axis=1), -np.inf), np.where(bounded, tri_x.max(axis=1), np.inf)
    lo_y, hi_y = np.where(bounded, tri_y.min(axis=1), -np.inf), np.where(bounded, tri_y.max(axis=1), np.inf)
    useful = (hi_x >= x0) & (lo_x <= x1) & (hi_y >= y0) & (lo_y <= y1)
    kept = np.flatnonzero(useful)
    cx0, cx1 = to_cell(lo_x[kept], x0, scale_x), to_cell(hi_x[kept], x0, scale_x)
    cy0, cy1 = to_cell(lo_y[kept], y0, scale_y), to_cell(hi_y[kept], y0, scale_y)
    best_s = np.full(n, np.inf)
    best_face = np.full(n, -1, dtype=np.int64)
    order = np.argsort(ray_cell, kind="stable")
    starts = np.searchsorted(ray_cell[order], np.arange(cells * cells + 1))
    for cell in np.flatnonzero(np.diff(starts)):
        i, j = divmod(int(cell), cells)
        faces = kept[(cx0 <= i) & (i <= cx1) & (cy0 <= j) & (j <= cy1)]
        if len(faces) == 0:
            continue
        rays = order[starts[cell]:starts[cell + 1]]
        s, face = moller_trumbore(origin, directions[rays], triangles[faces])
        best_s[rays] = s
        best_face[rays] = np.where(face >= 0, faces[np.maximum(face, 0)], -1)
    return best_s, best_face


def _embree_available() -> bool:
    """Whether Embree can be used: ``embreex`` imports (``trimesh.ray`` hides the failure behind a
    wrapper)."""
    try:
        import embreex  # noqa: F401
        from trimesh.ray.ray_pyembree import RayMeshIntersector  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass(frozen=True, eq=False, init=False)
class MeshObject:
    """A triangle mesh (``trimesh.Trimesh``, world coordinates) with a texture, vertex colours or one
    colour.

    Appearance, first that applies: ``texture`` with per-vertex ``uv`` ``(V, 2)`` (trimesh's
    convention, v = 0 at the bottom of the image; taken from ``mesh.visual`` when it has a
    texture and none is given); ``texture`` without uv, projected triplanarly (each face takes the
    two world axes most parallel to it, one tile per ``texture_scale`` metres); the mesh's vertex
    or face colours; ``color``. Normals are interpolated from the vertices where they agree with
    the face's within 30 degrees (smooth surfaces) and are the face's elsewhere (creases).

    ``intersector`` picks the ray search: "auto" (Embree when ``embreex`` is installed, otherwise
    :func:`binned_moller_trumbore`), "embree" or "numpy".
    """

    # what the constructor stores (it takes an image for the texture, array-like uv)
    mesh: trimesh.Trimesh
    texture: Texture | None
    uv: np.ndarray | None
    texture_scale: float
    color: tuple[float, float, float]
    intersector: str
    name: str
    triangles: np.ndarray = field(repr=False)
    _cache: dict = field(repr=False)

    def __init__(self, mesh: trimesh.Trimesh, texture: Texture | np.ndarray | None = None,
                 uv: ArrayLike | None = None, texture_scale: float = 1.0,
                 color: tuple[float, float, float] = (0.6, 0.6, 0.6), intersector: str = "auto",
                 name: str = "mesh") -> None:
        import trimesh

        if not isinstance(mesh, trimesh.Trimesh):
            raise InvalidValue("mesh", f"expected a trimesh.Trimesh, got {type(mesh).__name__}")
        if len(mesh.faces) == 0:
            raise InvalidValue("mesh", "the mesh has no faces")
        if intersector not in ("auto", "embree", "numpy"):
            raise InvalidValue("intersector", f"must be auto, embree or numpy, got {intersector!r}")
        if intersector == "embree" and not _embree_available():
            raise InvalidValue("intersector", "Embree needs the embreex package, which is not installed")
        visual: Any = getattr(mesh, "visual", None)  # ColorVisuals or TextureVisuals: see .kind
        if getattr(visual, "kind", None) == "texture" and getattr(visual, "uv", None) is not None:
            if uv is None:
                uv = visual.uv
            if texture is None:
                material = visual.material
                image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
                texture = None if image is None else np.asarray(image)
        stored_texture = as_texture(texture)
        stored_uv = None
        if uv is not None:
            uv_array = np.asarray(uv, dtype=np.float64)
            if uv_array.shape != (len(mesh.vertices), 2) or not np.all(np.isfinite(uv_array)):
                raise InvalidValue("uv", f"expected ({len(mesh.vertices)}, 2) finite texture coordinates, "
                                         f"got shape {uv_array.shape}")
            stored_uv = _readonly(uv_array)
        _set_fields(self, mesh=mesh, texture=stored_texture, uv=stored_uv,
                    texture_scale=float(_positive(texture_scale, "texture_scale", 1)[0]),
                    color=_floats(_color(color)), intersector=intersector, name=name,
                    triangles=_readonly(mesh.vertices[mesh.faces]), _cache={})

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_cache"] = {}  # the Embree scene and derived tables are rebuilt on demand
        return state

    def __setstate__(self, state: dict) -> None:
        for key, value in state.items():
            object.__setattr__(self, key, value)

    # appearance tables, computed once
    def _tables(self) -> dict:
        if "normals" not in self._cache:
            mesh = self.mesh
            cache = self._cache
            cache["face_normals"] = np.asarray(mesh.face_normals, dtype=np.float64)
            cache["normals"] = np.asarray(mesh.vertex_normals, dtype=np.float64)[mesh.faces]  # (F, 3, 3)
            visual: Any = getattr(mesh, "visual", None)  # ColorVisuals or TextureVisuals: see .kind
            kind = getattr(visual, "kind", None)
            if self.texture is None and kind == "vertex":
                cache["colors"] = (np.asarray(visual.vertex_colors)[:, :3] / 255.0)[mesh.faces]
            elif self.texture is None and kind == "face":
                colors = np.asarray(visual.face_colors)[:, :3] / 255.0
                cache["colors"] = np.repeat(colors[:, None], 3, axis=1)
            if self.texture is not None and self.uv is not None:
                uv = np.stack([self.uv[:, 0], 1.0 - self.uv[:, 1]], axis=1)[mesh.faces]  # image rows down
                cache["uv"] = uv
                e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
                uv_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
                area = np.maximum(np.asarray(mesh.area_faces, dtype=np.float64), 1e-300)
                cache["density"] = np.sqrt(uv_area / area)
        return self._cache

    def hull(self) -> tuple[np.ndarray, np.ndarray]:
        lower, upper = self.mesh.bounds
        return _box_hull(0.5 * (lower + upper), np.eye(3), 0.5 * (upper - lower))

    def _search(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Face hit first by each ray (-1 for none): Embree or Moeller-Trumbore (see the class docstring)."""
        use_embree = self.intersector == "embree" or (self.intersector == "auto" and _embree_available())
        if not use_embree:
            return binned_moller_trumbore(origin, directions, np.asarray(self.triangles))[1]
        if "embree" not in self._cache:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            self._cache["embree"] = RayMeshIntersector(self.mesh)
        origins = np.broadcast_to(origin, directions.shape)
        return np.asarray(self._cache["embree"].intersects_first(origins, directions), dtype=np.int64)

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slab test on the bounding box, then the triangle search; ``s`` recomputed in float64 from the
        face plane."""
        s = np.full(len(directions), np.inf)
        faces = np.full(len(directions), -1, dtype=np.int64)
        lower, upper = self.mesh.bounds
        pad = 1e-9 * max(1.0, float(np.max(upper - lower)))
        entry, exit_ = slab(origin, directions, lower - pad, upper + pad)
        candidates = np.flatnonzero((entry <= exit_) & (exit_ >= NEAR))
        if len(candidates) == 0:
            return s, faces
        found = self._search(origin, directions[candidates])
        hit = found >= 0
        rays, found = candidates[hit], found[hit]
        normals = self._tables()["face_normals"][found]
        vertex = np.asarray(self.triangles)[found, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            exact = np.einsum("ij,ij->i", normals, vertex - origin) / np.einsum("ij,ij->i", normals,
                                                                                directions[rays])
        keep = np.isfinite(exact) & (exact >= NEAR)
        s[rays[keep]] = exact[keep]
        faces[rays[keep]] = found[keep]
        return s, faces

    def surface(self, points: np.ndarray, aux: np.ndarray) -> Surface:
        tables = self._tables()
        tri = np.asarray(self.triangles)[aux]
        weights = _barycentric(points, tri)
        face_normal = tables["face_normals"][aux]
        smooth = np.einsum("mk,mkj->mj", weights, tables["normals"][aux])
        smooth /= np.maximum(np.linalg.norm(smooth, axis=1, keepdims=True), 1e-300)
        crease = np.einsum("ij,ij->i", smooth, face_normal) < np.cos(np.radians(30.0))
        normal = np.where(crease[:, None], face_normal, smooth)
        if self.texture is not None and "uv" in tables:
            uv = np.einsum("mk,mkj->mj", weights, tables["uv"][aux])
            return Surface(normal, uv, tables["density"][aux])
        if self.texture is not None:
            axis = np.argmax(np.abs(face_normal), axis=1)
            first = np.where(axis == 0, 1, 0)
            second = np.where(axis == 2, 1, 2)
            rows = np.arange(len(points))
            offsets = np.array([[0.0, 0.0], [0.37, 0.61], [0.71, 0.13]])[axis]
            uv = np.stack([points[rows, first], -points[rows, second]], axis=1) / self.texture_scale + offsets
            return Surface(normal, uv, 1.0 / self.texture_scale)
        if "colors" in tables:
            color = np.einsum("mk,mkj->mj", weights, tables["colors"][aux]).astype(np.float32)
            return Surface(normal, color=color)
        return Surface(normal, color=_uniform(self.color, points.shape))


def _barycentric(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Barycentric weights ``(M, 3)`` of points ``(M, 3)`` in triangles ``(M, 3, 3)`` (clipped to the
    triangle)."""
    a = triangles[:, 0]
    e1, e2, p = triangles[:, 1] - a, triangles[:, 2] - a, points - a
    d11 = np.einsum("ij,ij->i", e1, e1)
    d12 = np.einsum("ij,ij->i", e1, e2)
    d22 = np.einsum("ij,ij->i", e2, e2)
    p1 = np.einsum("ij,ij->i", p, e1)
    p2 = np.einsum("ij,ij->i", p, e2)
    det = np.where(np.abs(d11 * d22 - d12 * d12) > 1e-300, d11 * d22 - d12 * d12, 1.0)
    w1 = np.clip((d22 * p1 - d12 * p2) / det, 0.0, 1.0)
    w2 = np.clip((d11 * p2 - d12 * p1) / det, 0.0, 1.0 - w1)
    return np.stack([1.0 - w1 - w2, w1, w2], axis=1)


SceneObject = Plane | Box | Sphere | MeshObject


# --- the scene ------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Scene:
    """A set of objects, a background colour and a light; metres, any right-handed world frame.

    ``light`` is the direction *towards* a distant light (None: unlit, every surface shows its
    albedo); a surface point's colour is ``albedo * (ambient + (1 - ambient) max(0, n . l))`` with
    its normal ``n`` turned towards the camera, which depends on the point only (not on the view),
    so every view sees the same colour at the same point. There are no shadows.
    ``background`` is the colour of rays that hit nothing. ``up`` (the world's vertical),
    ``center`` (the point of interest) and ``home`` (a good first viewpoint) are what the camera
    path generators use as defaults.
    """

    objects: tuple[SceneObject, ...]
    background: tuple[float, float, float] = (0.55, 0.7, 0.9)
    light: tuple[float, float, float] | None = (0.3, -0.45, 0.85)
    ambient: float = 0.5
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    home: tuple[float, float, float] | None = None
    name: str = "scene"

    def __post_init__(self) -> None:
        objects = tuple(self.objects)
        for k, item in enumerate(objects):
            if not isinstance(item, (Plane, Box, Sphere, MeshObject)):
                raise InvalidValue("objects", f"object {k} is a {type(item).__name__}, not a Plane, Box, "
                                              "Sphere or MeshObject")
        object.__setattr__(self, "objects", objects)
        object.__setattr__(self, "background", tuple(float(c) for c in _color(self.background, "background")))
        if self.light is not None:
            object.__setattr__(self, "light", tuple(float(c) for c in _unit(self.light, "light")))
        if not 0.0 <= float(self.ambient) <= 1.0:
            raise InvalidValue("ambient", f"must be in [0, 1], got {self.ambient!r}")
        object.__setattr__(self, "ambient", float(self.ambient))
        object.__setattr__(self, "up", tuple(float(c) for c in _unit(self.up, "up")))
        object.__setattr__(self, "center", tuple(float(c) for c in _vector(self.center, "center")))
        if self.home is not None:
            object.__setattr__(self, "home", tuple(float(c) for c in _vector(self.home, "home")))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds ``(lower (3,), upper (3,))`` of all objects (of their hulls)."""
        if not self.objects:
            return np.array(self.center), np.array(self.center)
        corners = np.concatenate([item.hull()[0] for item in self.objects])
        return corners.min(axis=0), corners.max(axis=0)


__all__ = ["NEAR", "Box", "MeshObject", "Plane", "Scene", "SceneObject", "Sphere", "Surface",
           "binned_moller_trumbore", "moller_trumbore", "slab"]
