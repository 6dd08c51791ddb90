"""Framing a tab's 3D camera: all the 3D content inside the canvas, as large as it fits, the first time there
is some, and again on "Fit view".

The content is the state's 3D values (point clouds, cameras, meshes ...:
:func:`lab.viewer.renderers.points_of`) and what the module's interactions draw (:meth:`Interaction.bounds`:
e.g. the four pose candidates of an epipolar pair beside the scene). The camera looks the way
:func:`lab.viewer.renderers.viewpoint` says (over the cameras' shoulders, else from the front and above);
:func:`fit_camera` then places it so that every content
point projects inside the canvas with a margin, centred, through a pinhole with the browser's vertical field
of view and the canvas's aspect (viser docks its panels beside the canvas: the canvas is the free part of
the window, and the client reports its size and fov on the camera handle).

A student's own camera moves are never undone by a redraw: the tab frames the first 3D content of a session,
and again only while the camera stands where the last fit put it: when the canvas changes shape (the image
panel appears), or the content no longer fits that view (Run all adds a cloud many times the size of what
was drawn before) or has shrunk to a speck.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lab.core.errors import InvalidValue
from lab.core.values import Cameras, PointCloud
from lab.viewer.interactions import Interaction
from lab.viewer.renderers import frustum_corners, points_of, scene_extent, viewpoint

log = logging.getLogger("lab.viewer")

#: three.js's (and viser's) default vertical field of view, used until the browser reports its own.
DEFAULT_FOV = math.radians(75.0)
#: The canvas between the viewer's two docked panels of a 1400 x 900 window (552 x 900), used until the
#: browser reports its canvas: a narrow guess, so the content fits a wider canvas too.
DEFAULT_ASPECT = 552.0 / 900.0
#: Share of the canvas (each way) the content's extent may take: the rest is margin.
FILL = 0.86
#: At most this many content points are kept for the fit (a random-free, evenly strided subset).
MAX_FIT_POINTS = 20000


@dataclass(frozen=True)
class Viewport:
    """The canvas a camera draws: vertical field of view ``fov`` (radians) and ``aspect`` (width / height)."""

    fov: float = DEFAULT_FOV
    aspect: float = DEFAULT_ASPECT

    def __post_init__(self) -> None:
        if not (0.0 < self.fov < math.pi) or not (self.aspect > 0.0 and math.isfinite(self.aspect)):
            raise InvalidValue("viewport", f"expected 0 < fov < pi and a positive aspect, got fov {self.fov} "
                                           f"and aspect {self.aspect}")


@dataclass(frozen=True)
class CameraPose:
    """Where a viewer camera is: ``position`` and ``look_at`` ``(3,)``, world up ``up`` ``(3,)`` (-y)."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray


def camera_axes(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``(3, 3)`` rows x (right), y (down), z (forward) of a camera looking along ``forward`` with world
    ``up`` at the top of the picture (OpenCV's camera axes, DESIGN.md 3)."""
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z)
    down = -np.asarray(up, dtype=np.float64)
    y = down - float(down @ z) * z
    if np.linalg.norm(y) < 1e-9:  # looking straight up or down: any down in the picture will do
        y = np.eye(3)[int(np.argmin(np.abs(z)))] - z * z[int(np.argmin(np.abs(z)))]
    y = y / np.linalg.norm(y)
    return np.stack([np.cross(y, z), y, z])


def fit_camera(points: np.ndarray, forward: np.ndarray, viewport: Viewport, *, fill: float = FILL,
               up: np.ndarray | None = None) -> CameraPose:
    """The closest camera looking along ``forward`` that sees all ``points`` ``(N, 3)``, centred.

    With the camera's axes ``x, y, z`` (:func:`camera_axes`) and each point's coordinates ``a = p.x``,
    ``b = p.y``, ``w = p.z``, a camera at ``e`` sees the point inside ``fill`` of the canvas when
    ``|a - e_x| <= k_x (w - e_z)`` with ``k_x = fill tan(fov / 2) aspect`` (``b`` and
    ``k_y = fill tan(fov / 2)`` alike). The largest ``e_z`` for which an ``e_x`` exists is
    ``(min(a + k_x w) - max(a - k_x w)) / (2 k_x)``, and ``e_x`` is the middle of that interval,
    ``(max(a - k_x w) + min(a + k_x w)) / 2``. The camera takes the smaller ``e_z`` of the two directions (and
    stays in front of the nearest point), then ``e_x`` and ``e_y`` that put the outermost points equally far
    from the left and right edges, and the top and bottom (:func:`_centred`). It looks at the point of its
    axis at the content's middle depth (what the mouse then orbits about).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    points = points[np.all(np.isfinite(points), axis=1)]
    if not len(points):
        raise InvalidValue("points", "no finite point to frame")
    if not 0.0 < fill <= 1.0:
        raise InvalidValue("fill", f"must be in (0, 1], got {fill}")
    world_up = np.array([0.0, -1.0, 0.0]) if up is None else np.asarray(up, dtype=np.float64)
    axes = camera_axes(forward, world_up)
    a, b, w = (points @ axes.T).T
    half = math.tan(viewport.fov / 2.0)
    kx, ky = fill * half * viewport.aspect, fill * half
    size = max(float(np.ptp(points, axis=0).max()), 1e-6)
    ez = min((float(np.min(a + kx * w)) - float(np.max(a - kx * w))) / (2.0 * kx),
             (float(np.min(b + ky * w)) - float(np.max(b - ky * w))) / (2.0 * ky),
             float(w.min()) - 0.05 * size)
    ex, ey = _centred(a, w - ez), _centred(b, w - ez)
    position = axes.T @ np.array([ex, ey, ez])
    middle = (float(w.min()) + float(w.max())) / 2.0
    look_at = position + axes[2] * max(middle - ez, 1e-3 * size)
    return CameraPose(position, look_at, world_up)


def _centred(across: np.ndarray, depth: np.ndarray) -> float:
    """The camera coordinate ``e`` across the view that centres the points ``across`` ``(N,)`` at ``depth``
    ``(N,)`` in front of it: ``max((c - e) / d) = -min((c - e) / d)`` (both sides decrease with ``e``;
    bisection to a millionth of the content's width)."""
    depth = np.maximum(depth, 1e-12)
    lo, hi = float(across.min()), float(across.max())
    tolerance = 1e-6 * max(hi - lo, 1e-12)
    while hi - lo > tolerance:
        e = (lo + hi) / 2.0
        ratio = (across - e) / depth
        if float(ratio.max() + ratio.min()) > 0.0:
            lo = e
        else:
            hi = e
    return (lo + hi) / 2.0


def project(points: np.ndarray, pose: CameraPose, viewport: Viewport) -> np.ndarray:
    """``(N, 2)`` canvas coordinates in [0, 1] (x right, y down; outside when out of view) of ``points``
    ``(N, 3)`` seen by ``pose`` through ``viewport``'s pinhole; NaN for a point behind the camera."""
    axes = camera_axes(pose.look_at - pose.position, pose.up)
    local = (np.asarray(points, dtype=np.float64).reshape(-1, 3) - pose.position) @ axes.T
    half = math.tan(viewport.fov / 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = local[:, 0] / local[:, 2] / (half * viewport.aspect)
        y = local[:, 1] / local[:, 2] / half
    out = np.stack([(x + 1.0) / 2.0, (y + 1.0) / 2.0], axis=1)
    out[local[:, 2] <= 0] = np.nan
    return out


#: A framed view still fits content that lies inside this share of the canvas each way and spans at least
#: :data:`MIN_SPAN` of it one way.
STILL_FITS = 0.98
MIN_SPAN = 0.3


def fits(points: np.ndarray, pose: CameraPose, viewport: Viewport) -> bool:
    """Whether ``points`` ``(N, 3)`` seen by ``pose`` lie in front of it, inside :data:`STILL_FITS` of the
    canvas, and span at least :data:`MIN_SPAN` of it (else the tab's camera is framed again)."""
    xy = project(points, pose, viewport)
    if not len(xy) or not np.all(np.isfinite(xy)):
        return False
    margin = (1.0 - STILL_FITS) / 2.0
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return bool(np.all(lo >= margin) and np.all(hi <= 1.0 - margin) and float((hi - lo).max()) >= MIN_SPAN)


def robust_points(values: Iterable[Any]) -> np.ndarray:
    """``(N, 3)`` points that bound the drawn 3D ``values``: their finite points with a few far outliers (a
    triangulated point at infinity) dropped: those outside the 1st-99th percentile box widened by half of
    it, when there are more than 100; at most :data:`MAX_FIT_POINTS`, evenly strided."""
    chunks = [p for p in (points_of(v) for v in values) if p is not None and len(p)]
    if not chunks:
        return np.zeros((0, 3))
    points = np.concatenate(chunks).astype(np.float64)
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) > 100:
        lo, hi = np.percentile(points, [1, 99], axis=0)
        pad = 0.5 * (hi - lo)
        points = points[np.all((points >= lo - pad) & (points <= hi + pad), axis=1)]
    if len(points) > MAX_FIT_POINTS:
        points = points[::math.ceil(len(points) / MAX_FIT_POINTS)]
    return points


def box_corners(box: np.ndarray) -> np.ndarray:
    """The 8 corners ``(8, 3)`` of a ``(2, 3)`` min / max box."""
    lo, hi = np.asarray(box, dtype=np.float64).reshape(2, 3)
    return np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
                     for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def framing(state: Mapping[str, Any], interactions: Iterable[Interaction] = (),
            viewport: Viewport | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """``(eye, look_at)`` for a tab's camera showing everything drawn in 3D in ``viewport`` (default: the
    viewer's canvas in a 1400 x 900 window); None when there is nothing in 3D yet."""
    pose = frame_pose(state, interactions, viewport or Viewport())
    return None if pose is None else (pose.position, pose.look_at)


def aim(state: Mapping[str, Any],
        interactions: Iterable[Interaction] = ()) -> tuple[np.ndarray, np.ndarray] | None:
    """What to frame and which way to look: the content points ``(N, 3)`` (:func:`robust_points` of the
    state's values, the corners of its camera frustums' pictures, and the corners of each interaction's
    :meth:`~Interaction.bounds`; each frustum whole, apex included) and the
    viewing direction ``(3,)`` of :func:`viewpoint` over the state's values and the interactions' boxes; None
    when nothing is drawn in 3D."""
    interactions = list(interactions)
    boxes = [b for b in (i.bounds() for i in interactions) if b is not None and np.all(np.isfinite(b))]
    extent = scene_extent(state.values())  # what the frustums are drawn the size of
    # each frustum whole: its picture's corners and its apex (the camera centre), never dropped as outliers
    # (a NeRF scene's dense mesh outnumbers its cameras a thousand to one)
    glyphs = [np.concatenate([frustum_corners(v, extent), v.centers]) for v in state.values()
              if isinstance(v, Cameras)]
    points = np.concatenate([robust_points(state.values()), *glyphs, *(box_corners(b) for b in boxes)])
    if not len(points):
        return None
    view = viewpoint([*state.values(), *(PointCloud(box_corners(b)) for b in boxes)])
    forward = (view[1] - view[0]) if view is not None else np.array([-0.35, 0.6, 1.1])
    return points, forward


def frame_pose(state: Mapping[str, Any], interactions: Iterable[Interaction],
               viewport: Viewport) -> CameraPose | None:
    """The :class:`CameraPose` that fits everything drawn in 3D (:func:`aim`) into ``viewport``; None when
    nothing is drawn in 3D."""
    aimed = aim(state, interactions)
    return None if aimed is None else fit_camera(aimed[0], aimed[1], viewport)


def client_viewport(camera: Any) -> Viewport | None:
    """The browser's :class:`Viewport` from a viser camera handle (its fov and canvas size), or None before
    the browser has reported its camera."""
    try:
        fov, width, height = float(camera.fov), float(camera.image_width), float(camera.image_height)
    except (AssertionError, AttributeError, TypeError, ValueError):  # viser asserts until the client reports
        return None
    if not (0.0 < fov < math.pi) or width <= 0 or height <= 0:
        return None
    return Viewport(fov, width / height)


class CameraFramer:
    """Frames the camera of one browser tab (``target``: a viser ``ClientHandle``) once per session.

    The fit is kept with the viewport it used: when the browser reports a canvas of another shape (or its
    first report, when the fit had to guess) and the camera still stands where the fit put it, the same
    content is framed again for the new canvas.
    """

    def __init__(self, target: Any, *, is_client: bool) -> None:
        self.target = target
        self.is_client = is_client
        self.framed = False
        self._lock = threading.Lock()
        #: The last fit: its content points, direction, viewport (None: guessed, the browser had not reported
        #: its canvas yet), and the pose it set; None before the first fit.
        self._fit: tuple[np.ndarray, np.ndarray, Viewport | None, CameraPose] | None = None
        if is_client:
            try:
                target.camera.on_update(self._camera_moved)
            except Exception as exc:  # cosmetic: the fit then never adapts to a new canvas
                log.info("could not follow the camera: %s", exc)

    def reset(self) -> None:
        """A new session is shown: frame its content when it has some."""
        self.framed = False

    def frame(self, state: Mapping[str, Any], interactions: Iterable[Interaction]) -> None:
        """Point the camera at the 3D content the first time there is some, and again while the camera stands
        where the last fit put it and the content no longer fits that view (epipolar's rig is drawn from the
        truth before any step; Run all then adds a cloud many times its size) or has shrunk to a speck."""
        if not self.is_client:
            return
        if not self.framed:
            self.fit(state, interactions)
            return
        with self._lock:
            fit = self._fit
        if fit is None or not self._untouched(fit[3]):
            return
        aimed = aim(state, interactions)
        if aimed is not None and not fits(aimed[0], fit[3], fit[2] or Viewport()):
            self._apply(*aimed, client_viewport(self.target.camera))

    def _untouched(self, pose: CameraPose) -> bool:
        """Whether the tab's camera stands where ``pose`` put it (True before the browser reported it)."""
        try:
            position = np.asarray(self.target.camera.position, dtype=np.float64)
        except AssertionError:  # viser asserts until the browser has reported its camera
            return True
        return bool(np.linalg.norm(position - pose.position)
                    <= 1e-3 * max(float(np.linalg.norm(pose.look_at - pose.position)), 1e-12))


    def fit(self, state: Mapping[str, Any], interactions: Iterable[Interaction]) -> None:
        """Point the camera at all the 3D content now (the "Fit view" button), whatever was done before."""
        if not self.is_client:
            return
        aimed = aim(state, interactions)
        if aimed is None:
            return
        self.framed = True
        self._apply(*aimed, client_viewport(self.target.camera))

    def _apply(self, points: np.ndarray, forward: np.ndarray, viewport: Viewport | None) -> None:
        """Fit ``points`` seen along ``forward`` into ``viewport`` (None: :class:`Viewport`'s defaults)."""
        pose = fit_camera(points, forward, viewport or Viewport())
        with self._lock:
            self._fit = (points, forward, viewport, pose)
        try:
            camera = self.target.camera
            camera.up_direction = tuple(pose.up)
            camera.position = tuple(pose.position)
            camera.look_at = tuple(pose.look_at)  # after the position, which drags look_at along
        except Exception as exc:  # cosmetic (viser refuses before the browser reported its camera)
            log.info("could not frame the camera: %s", exc)

    def _camera_moved(self, camera: Any) -> None:
        """viser's camera callback: frame the last fit again for a canvas of another shape, unless the student
        has moved the camera since."""
        with self._lock:
            fit = self._fit
        now = client_viewport(camera)
        if fit is None or now is None:
            return
        points, forward, used, pose = fit
        if used is not None and math.isclose(now.aspect, used.aspect, rel_tol=0.01) \
                and math.isclose(now.fov, used.fov, rel_tol=0.01):
            return
        if used is not None and not self._untouched(pose):
            return
        self._apply(points, forward, now)


__all__ = ["DEFAULT_ASPECT", "DEFAULT_FOV", "FILL", "MIN_SPAN", "STILL_FITS", "CameraFramer", "CameraPose",
           "Viewport", "aim", "box_corners", "camera_axes", "client_viewport", "fit_camera", "fits",
           "frame_pose", "framing", "project", "robust_points"]
