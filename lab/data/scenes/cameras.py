"""Camera paths for the synthetic scenes: an orbit, forward motion and a stereo rig.

Each generator returns :class:`lab.core.Cameras` (OpenCV convention, ``X_c = R X_w + t``) with one
intrinsic matrix per view. Orientation comes from :func:`lab.geometry.rotations.look_at` with the
scene's ``up`` direction (a scene's z axis by default), so image rows run down the world's
vertical. Intrinsics are given as ``K`` or built from ``fx`` (default: a 60 degree horizontal field
of view), ``width`` and ``height`` (the image size in pixels) with the principal point at the
image centre ``((width - 1) / 2, (height - 1) / 2)``.

Random perturbations (``jitter``) come from ``numpy.random.default_rng(seed)``: the same seed gives
the same cameras.
"""

from __future__ import annotations

from numbers import Integral, Real

import numpy as np

from lab.core.errors import InvalidValue
from lab.core.values import Cameras
from lab.data.scenes.objects import Scene
from lab.geometry.camera import as_distortion, as_intrinsics
from lab.geometry.rotations import look_at

#: Default horizontal field of view, degrees.
DEFAULT_FOV_DEG = 60.0


def intrinsics(*, width: int = 640, height: int = 480, fx: float | None = None, fy: float | None = None,
               cx: float | None = None, cy: float | None = None) -> np.ndarray:
    """A ``(3, 3)`` camera matrix: ``fx`` defaults to a 60 degree horizontal field of view, ``fy`` to
    ``fx``, the principal point to the image centre ``((width - 1) / 2, (height - 1) / 2)`` (pixel
    centres at integers)."""
    width, height = _image_size(width, height)
    fx = width / (2.0 * np.tan(np.radians(DEFAULT_FOV_DEG) / 2.0)) if fx is None else _positive(fx, "fx")
    fy = fx if fy is None else _positive(fy, "fy")
    cx = (width - 1) / 2.0 if cx is None else _finite(cx, "cx")
    cy = (height - 1) / 2.0 if cy is None else _finite(cy, "cy")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def orbit_cameras(scene_or_center: Scene | np.ndarray | tuple | None = None, *, num_views: int = 8,
                  radius: float | None = None, elevation: float | None = None, arc_deg: float = 360.0,
                  start_deg: float | None = None, look_at_point: np.ndarray | tuple | None = None,
                  up: np.ndarray | tuple | None = None, K: np.ndarray | None = None, fx: float | None = None,
                  width: int = 640, height: int = 480, dist: np.ndarray | None = None, jitter: float = 0.0,
                  seed: int = 0) -> Cameras:
    """Cameras on a circle around a point, all looking at it.

    The circle has ``radius`` (metres) about the axis ``up`` through the centre, raised by
    ``elevation`` metres along ``up``; view ``i`` sits at azimuth ``start_deg + arc_deg i / V``
    (a full turn) or ``start_deg + arc_deg i / (V - 1)`` (a partial arc, ends included), azimuth 0
    being the direction of the first world axis not parallel to ``up`` and 90 degrees
    ``up x`` that. The centre is ``scene_or_center`` (a point, or a :class:`Scene`'s ``center``;
    default the origin); a scene also supplies ``up`` and, from its ``home`` viewpoint, the
    default radius, elevation and start azimuth (so view 0 is taken from ``home``; otherwise 3 m,
    1 m and 0 degrees). Cameras look at ``look_at_point`` (default: the centre). ``jitter``
    (metres) adds Gaussian noise of that standard deviation to every eye and look-at point.

    ``width`` and ``height`` are the image size in pixels (the camera's height is ``elevation``).
    """
    scene, centre = _scene_and_point(scene_or_center)
    up = _up(up, scene)
    num_views = _count(num_views, "num_views")
    first, second = _horizontal_basis(up)
    home = None if scene is None or scene.home is None else np.asarray(scene.home) - centre
    vertical = 1.0 if home is None else float(home @ up)
    horizontal = None if home is None else home - vertical * up
    if radius is None:
        radius = 3.0 if horizontal is None else float(np.linalg.norm(horizontal))
    if elevation is None:
        elevation = vertical
    if start_deg is None:
        start_deg = 0.0 if horizontal is None or np.linalg.norm(horizontal) < 1e-9 \
            else float(np.degrees(np.arctan2(horizontal @ second, horizontal @ first)))
    radius = _positive(radius, "radius")
    elevation = _finite(elevation, "elevation")
    arc = np.radians(_finite(arc_deg, "arc_deg"))
    steps = np.arange(num_views) / (num_views if np.isclose(abs(arc_deg), 360.0) or num_views == 1
                                    else num_views - 1)
    azimuth = np.radians(_finite(start_deg, "start_deg")) + arc * steps
    eyes = (centre + radius * (np.cos(azimuth)[:, None] * first + np.sin(azimuth)[:, None] * second)
            + elevation * up)
    target = centre if look_at_point is None else _point(look_at_point, "look_at_point")
    targets = np.broadcast_to(target, eyes.shape).copy()
    eyes, targets = _jittered(eyes, targets, jitter, seed)
    R, t = look_at(eyes, targets, up)
    return _cameras(R, t, K=K, fx=fx, width=width, height=height, dist=dist)


def forward_cameras(*, num_views: int = 5, step: float = 0.1, scene: Scene | None = None,
                    start: np.ndarray | tuple | None = None, direction: np.ndarray | tuple | None = None,
                    up: np.ndarray | tuple | None = None, turn_deg: float = 0.0,
                    K: np.ndarray | None = None, fx: float | None = None, width: int = 640, height: int = 480,
                    dist: np.ndarray | None = None, jitter: float = 0.0, seed: int = 0) -> Cameras:
    """Cameras moving forward: view ``i`` at ``start + i step direction``, looking along ``direction``
    turned by ``i turn_deg`` degrees about ``up`` (positive turns left, towards ``up x direction``).

    Defaults come from ``scene``: ``start`` its ``home`` viewpoint, ``direction`` the horizontal
    direction from there to its ``center``, ``up`` its ``up``; without a scene, start at the origin,
    move along the first world axis not parallel to ``up``, with ``up`` = z. ``jitter`` (metres)
    perturbs the positions and look-at points.
    """
    up = _up(up, scene)
    num_views = _count(num_views, "num_views")
    step = _finite(step, "step")
    if start is None:
        start = np.zeros(3) if scene is None or scene.home is None else np.asarray(scene.home)
    start = _point(start, "start")
    if direction is None and scene is not None:
        towards = np.asarray(scene.center) - start
        direction = towards - (towards @ up) * up  # horizontal
    direction = _horizontal_basis(up)[0] if direction is None else _point(direction, "direction")
    norm = np.linalg.norm(direction)
    if norm < 1e-12 or np.linalg.norm(np.cross(direction / norm, up)) < 1e-9:
        raise InvalidValue("direction", "must be a non-zero direction not parallel to up")
    direction = direction / norm
    eyes = start + (step * np.arange(num_views))[:, None] * direction
    angles = np.radians(_finite(turn_deg, "turn_deg")) * np.arange(num_views)
    side = np.cross(up, direction)
    heading = np.cos(angles)[:, None] * direction + np.sin(angles)[:, None] * side
    eyes, targets = _jittered(eyes, eyes + heading, jitter, seed)
    R, t = look_at(eyes, targets, up)
    return _cameras(R, t, K=K, fx=fx, width=width, height=height, dist=dist)


def stereo_rig(*, baseline: float = 0.1, scene: Scene | None = None, eye: np.ndarray | tuple | None = None,
               target: np.ndarray | tuple | None = None, up: np.ndarray | tuple | None = None,
               verge_deg: float = 0.0, K: np.ndarray | None = None, K_right: np.ndarray | None = None,
               fx: float | None = None, width: int = 640, height: int = 480, dist: np.ndarray | None = None,
               dist_right: np.ndarray | None = None) -> Cameras:
    """Two cameras: the left at ``eye`` looking at ``target``, the right ``baseline`` metres along the
    left's x axis.

    With ``verge_deg = 0`` both share the rotation (a rectified pair: ``x_right = x_left - f B / Z``
    for equal ``K``). A positive ``verge_deg`` toes both in by half of it each, about their own y
    axes, so the optical axes converge. ``K_right`` / ``dist_right`` give the right camera other
    intrinsics (default: the left's). ``eye`` and ``target`` default to the scene's ``home`` and
    ``center`` (without a scene: 3 m along -y from the origin, looking at it, z up).
    """
    up = _up(up, scene)
    baseline = _finite(baseline, "baseline")
    if baseline == 0.0:
        raise InvalidValue("baseline", "must be non-zero (both cameras would coincide)")
    if eye is None:
        eye = (0.0, -3.0, 0.0) if scene is None or scene.home is None else scene.home
    if target is None:
        target = np.zeros(3) if scene is None else scene.center
    eye, target = _point(eye, "eye"), _point(target, "target")
    R_left, _ = look_at(eye, target, up)
    right_eye = eye + baseline * R_left[0]
    half = np.radians(_finite(verge_deg, "verge_deg")) / 2.0
    rotations = np.stack([_toe_in(half) @ R_left, _toe_in(-half) @ R_left])
    centres = np.stack([eye, right_eye])
    t = -np.einsum("vij,vj->vi", rotations, centres)
    K_left = intrinsics(width=width, height=height, fx=fx) if K is None else as_intrinsics(K)
    K_pair = np.stack([K_left, K_left if K_right is None else as_intrinsics(K_right)])
    d_left = as_distortion(dist)
    dists = np.stack([d_left, d_left if dist_right is None else as_distortion(dist_right)])
    width, height = _image_size(width, height)
    return Cameras(K_pair, rotations, t, width, height, dist=dists if np.any(dists) else None)


# --- helpers ----------------------------------------------------------------------------------------------
def _toe_in(angle: float) -> np.ndarray:
    """Rotation of a camera about its own y axis turning its optical axis towards its +x by ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def _cameras(R: np.ndarray, t: np.ndarray, *, K: np.ndarray | None, fx: float | None, width: int, height: int,
             dist: np.ndarray | None) -> Cameras:
    width, height = _image_size(width, height)
    K = intrinsics(width=width, height=height, fx=fx) if K is None else as_intrinsics(K)
    views = len(R)
    d = as_distortion(dist)
    return Cameras(np.broadcast_to(K, (views, 3, 3)).copy(), R, t, width, height,
                   dist=np.broadcast_to(d, (views, 5)).copy() if np.any(d) else None)


def _jittered(eyes: np.ndarray, targets: np.ndarray, jitter: float,
              seed: int) -> tuple[np.ndarray, np.ndarray]:
    jitter = _finite(jitter, "jitter")
    if jitter < 0:
        raise InvalidValue("jitter", f"must be non-negative, got {jitter!r}")
    if jitter == 0:
        return eyes, targets
    rng = np.random.default_rng(seed)
    return eyes + rng.normal(0.0, jitter, eyes.shape), targets + rng.normal(0.0, jitter, targets.shape)


def _horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to ``up`` and to each other.

    The first world axis not parallel to ``up``, with its ``up`` component removed; then ``up x first``.
    """
    for axis in np.eye(3):
        first = axis - (axis @ up) * up
        if np.linalg.norm(first) > 1e-6:
            first = first / np.linalg.norm(first)
            return first, np.cross(up, first)
    raise AssertionError("unreachable: some world axis is not parallel to a unit vector")


def _scene_and_point(value: object) -> tuple[Scene | None, np.ndarray]:
    if isinstance(value, Scene):
        return value, np.asarray(value.center, dtype=np.float64)
    if value is None:
        return None, np.zeros(3)
    return None, _point(value, "scene_or_center")


def _up(up: object, scene: Scene | None) -> np.ndarray:
    if up is None:
        up = (0.0, 0.0, 1.0) if scene is None else scene.up
    vector = _point(up, "up")
    norm = np.linalg.norm(vector)
    if norm < 1e-12:
        raise InvalidValue("up", "must be a non-zero vector")
    return vector / norm


def _point(value: object, name: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InvalidValue(name, f"expected 3 numbers (or a Scene), got {value!r}") from None
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise InvalidValue(name, f"expected 3 finite numbers, got {value!r}")
    return array


def _finite(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, Real) or not np.isfinite(np.asarray(value)):
        raise InvalidValue(name, f"must be a finite number, got {value!r}")
    return float(value)


def _positive(value: object, name: str) -> float:
    number = _finite(value, name)
    if number <= 0:
        raise InvalidValue(name, f"must be positive, got {value!r}")
    return number


def _count(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, Integral) or value < 1:
        raise InvalidValue(name, f"must be a positive integer, got {value!r}")
    return int(value)


def _image_size(width: object, height: object) -> tuple[int, int]:
    return _pixels(width, "width"), _pixels(height, "height")


def _pixels(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, Integral) or value < 2:
        raise InvalidValue(name, f"the image {name} is a whole number of pixels (at least 2), got {value!r}; "
                                 "an orbit's camera height above its centre is `elevation`")
    return int(value)


__all__ = ["DEFAULT_FOV_DEG", "forward_cameras", "intrinsics", "orbit_cameras", "stereo_rig"]
