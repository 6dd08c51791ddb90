"""Interactions of the epipolar module: what the old epipolar-geometry Java applets had, in the viewer.

* **Click a pixel** of image 1 (or 2): its epipolar line in the other image, drawn on that image,
  and its ray in 3D from the camera's centre through the pixel, with the epipolar plane (both
  centres and the ray) cutting camera 2's image plane along that same line. The pixel comes from
  a click on the image shown as a plane in the camera's frustum in the 3D scene (viser scene
  images are clickable, GUI images are not), or from the number inputs (scripts, tests).
* **Drag a 3D point** (a transform gizmo, or the number inputs): its projections in both images,
  the epipolar plane through both camera centres and the point, and both epipolar lines move.
* **The four pose candidates** of E side by side (four small copies of the two-camera rig with
  the points triangulated by each, along the x axis), the one passing the cheirality test
  highlighted, with how many points each puts in front of both cameras.
* **Inliers and outliers** of RANSAC: the matches drawn across the image pair, inliers green,
  outliers red (the generic drawing shows keypoints and a sample of epipolar lines, not which
  matches RANSAC kept).

Which geometry is shown: the session's own F, E, candidates and pose once it has computed them,
else the dataset's ground truth (``session.truth``) when it has one; each folder says which.
World coordinates are camera 1's frame (the module's convention, and the generic drawing's):
camera 2 sees ``X_2 = R X_1 + t``.

The math is in the typed functions below (tested directly); the classes only wire it to viser.
Reference: R. Hartley and A. Zisserman, Multiple View Geometry (2nd ed., 2004): section 6.2.2
(back-projection of a pixel to a ray), 9.1 (the epipolar plane and lines), 9.6.2-9.6.3 (the four
solutions of E and the cheirality test).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Callable, Literal, Mapping

import cv2
import numpy as np

from lab.core.errors import InvalidValue, LabError, MissingInput
from lab.core.values import Image, ImageSet, Points2D, Segments2D
from lab.geometry.camera import pixels_to_normalized
from lab.geometry.homogeneous import to_homogeneous
from lab.geometry.triangulation import point_depths, projection_matrix, triangulate_dlt
from lab.modules.epipolar import (cheirality_counts, clip_lines, epipolar_lines, epipoles, essential_candidates,
                                  evaluate_fundamental)
from lab.viewer.interactions import NamedHandles
from lab.viewer.interactions import Interaction, InteractionContext
from lab.viewer.renderers import FRUSTUM_MAX_SIDE, PANEL_MAX_SIDE, PANEL_MIN_SIDE, overlay_view, to_rgb8

#: Colours (RGB, 0-255) of what the interactions draw.
PICK_COLOR = (255, 210, 0)
POINT_COLOR = (255, 0, 200)
CAMERA_COLORS = ((40, 90, 200), (230, 120, 20))
CHOSEN_COLOR = (30, 190, 60)
OTHER_COLOR = (150, 150, 150)
IN_FRONT_COLOR = (40, 120, 255)
BEHIND_COLOR = (230, 40, 40)
INLIER_COLOR = (30, 200, 60)
OUTLIER_COLOR = (235, 40, 40)
UNCLASSIFIED_COLOR = (255, 210, 0)

#: Most points per candidate drawn in 3D, and most match lines drawn on the image pair.
MAX_CANDIDATE_POINTS = 300
MAX_MATCH_LINES = 400


# ----------------------------------------------------------------------------------------------------
# Pure math
# ----------------------------------------------------------------------------------------------------
def camera_centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The centre ``C = -R^T t`` ``(3,)`` of a camera with ``X_c = R X + t`` (H&Z section 6.2.4)."""
    R = np.asarray(R, dtype=np.float64)
    return -R.T @ np.asarray(t, dtype=np.float64).reshape(3)


def pixel_ray(K: np.ndarray, R: np.ndarray, t: np.ndarray, pixel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Back-projection of a pixel: the ray's origin (the camera centre) and unit direction, ``(3,)`` each, in world.

    ``X(s) = C + s d`` with ``C = -R^T t`` and ``d ~ R^T K^-1 (u, v, 1)``: every point on it projects to
    ``(u, v)``; ``s > 0`` is in front of the camera. Reference: H&Z section 6.2.2 (eq. 6.14).
    """
    K = np.asarray(K, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    direction = R.T @ np.linalg.solve(K, to_homogeneous(np.asarray(pixel, dtype=np.float64).reshape(1, 2))[0])
    return camera_centre(R, t), direction / np.linalg.norm(direction)


def lift_pixels(K: np.ndarray, R: np.ndarray, t: np.ndarray, pixels: np.ndarray, depth: float) -> np.ndarray:
    """The world points ``(N, 3)`` at camera depth ``depth`` (``Z_c = depth``) that project to ``pixels`` ``(N, 2)``.

    ``X = R^T (depth K^-1 (u, v, 1) - t)``: the pixels placed on the image plane drawn at that depth.
    """
    K = np.asarray(K, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    rays = to_homogeneous(np.asarray(pixels, dtype=np.float64).reshape(-1, 2)) @ np.linalg.inv(K).T
    rays = rays / rays[:, 2:]
    return (depth * rays - np.asarray(t, dtype=np.float64).reshape(3)) @ R


def click_to_pixel(ray_origin: np.ndarray, ray_direction: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                   depth: float) -> np.ndarray:
    """The pixel ``(2,)`` where a click's ray (world) meets a camera's image plane drawn at depth ``depth``.

    In the camera frame the ray is ``o + s d`` (``o = R o_w + t``, ``d = R d_w``); it meets the plane
    ``Z_c = depth`` at ``s = (depth - o_z) / d_z``, and that point projects to ``K (X / Z)``. Raises
    :class:`InvalidValue` when the ray is parallel to the plane or meets it behind the viewer.
    """
    R = np.asarray(R, dtype=np.float64)
    origin = R @ np.asarray(ray_origin, dtype=np.float64).reshape(3) + np.asarray(t, dtype=np.float64).reshape(3)
    direction = R @ np.asarray(ray_direction, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(origin)) and np.all(np.isfinite(direction))) or abs(direction[2]) < 1e-12:
        raise InvalidValue("click", "the click's ray does not cross the image plane (seen edge-on)")
    s = (depth - origin[2]) / direction[2]
    if s <= 0:
        raise InvalidValue("click", "the image plane is behind the viewer along the click's ray")
    point = origin + s * direction
    pixel = np.asarray(K, dtype=np.float64) @ (point / point[2])
    return pixel[:2]


def project_point(K: np.ndarray, R: np.ndarray, t: np.ndarray, point: np.ndarray) -> tuple[np.ndarray, float]:
    """The pixel ``(2,)`` of a world point ``(3,)`` and its depth ``Z_c`` (negative: behind the camera).

    ``x ~ K (R X + t)`` (H&Z eq. 6.8); corresponds to ``cv2.projectPoints``. A point on the camera
    plane (``Z_c = 0``) has no pixel: :class:`InvalidValue`.
    """
    camera = np.asarray(R, dtype=np.float64) @ np.asarray(point, dtype=np.float64).reshape(3) + \
        np.asarray(t, dtype=np.float64).reshape(3)
    if abs(camera[2]) < 1e-12:
        raise InvalidValue("point", "lies on a camera's plane (depth 0): it has no image")
    pixel = np.asarray(K, dtype=np.float64) @ (camera / camera[2])
    return pixel[:2], float(camera[2])


def epipolar_plane_corners(c1: np.ndarray, c2: np.ndarray, point: np.ndarray, *, extend: float = 1.25) -> np.ndarray:
    """A quad ``(4, 3)`` of the epipolar plane of ``point``: ``c1``, ``c2``, then past ``point`` along both rays.

    The plane through both camera centres and a point contains both rays to the point, so it meets
    each image plane in that point's epipolar line (H&Z section 9.1, figure 9.1). Corners:
    ``c1``, ``c2``, ``c2 + extend (X - c2)``, ``c1 + extend (X - c1)``. A point on the baseline
    spans no plane: :class:`InvalidValue`.
    """
    c1, c2, X = (np.asarray(v, dtype=np.float64).reshape(3) for v in (c1, c2, point))
    normal = np.cross(c2 - c1, X - c1)
    scale = np.linalg.norm(c2 - c1) * np.linalg.norm(X - c1)
    if scale == 0 or np.linalg.norm(normal) <= 1e-9 * scale:
        raise InvalidValue("point", "lies on the baseline (the line through both camera centres): it spans no "
                                    "epipolar plane and projects onto the epipoles")
    return np.stack([c1, c2, c2 + extend * (X - c2), c1 + extend * (X - c1)])


@dataclass(frozen=True)
class ImagePlacement:
    """Where a camera's image is drawn in the scene: the plane ``Z_c = depth`` of its frustum."""

    position: np.ndarray  # (3,) world position of the image's centre
    rotation: np.ndarray  # (3, 3) camera to world (R^T): the plane's x, y axes are the image's u, v
    render_width: float
    render_height: float
    corners: np.ndarray  # (4, 3) world corners: top-left, top-right, bottom-right, bottom-left


def image_placement(K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int,
                    depth: float) -> ImagePlacement:
    """Place a ``width x height`` image on the plane ``Z_c = depth`` of a camera, so each pixel covers its ray.

    The image spans pixel edges ``[-0.5, width - 0.5] x [-0.5, height - 0.5]`` (pixel centres are
    integers, DESIGN.md 3); lifted to depth ``depth`` (:func:`lift_pixels`) it is ``depth width / fx``
    by ``depth height / fy``. viser draws a scene image in its node's x-y plane with u along +x and v
    along +y, so the node takes the camera's orientation ``R^T``. Exact for ``K`` without skew.
    """
    K = np.asarray(K, dtype=np.float64)
    corners_px = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    corners = lift_pixels(K, R, t, corners_px, depth)
    centre = lift_pixels(K, R, t, np.array([[(width - 1) / 2.0, (height - 1) / 2.0]]), depth)[0]
    return ImagePlacement(centre, np.asarray(R, dtype=np.float64).T, depth * width / K[0, 0],
                          depth * height / K[1, 1], corners)


def candidate_layout(count: int, spacing: float, *, axis: int = 0, first: float = 1.0) -> np.ndarray:
    """Offsets ``(count, 3)`` of the copies of a rig drawn side by side: ``(first + i) spacing`` along ``axis``.

    With ``first = 1`` the row starts one spacing beside the rig itself (which stays at the origin).
    """
    if count < 0 or not np.isfinite(spacing) or spacing <= 0:
        raise InvalidValue("spacing", f"expected a positive spacing and a count >= 0, got {spacing} and {count}")
    offsets = np.zeros((count, 3))
    offsets[:, axis] = (first + np.arange(count)) * spacing
    return offsets


def candidate_points(candidates: np.ndarray, K1: np.ndarray, K2: np.ndarray, x1: np.ndarray,
                     x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs triangulated by each candidate pose and whether each lies in front of both cameras.

    For each ``[R | t]`` of ``candidates`` ``(C, 3, 4)``: DLT triangulation of ``x1``, ``x2`` ``(N, 2)``
    with ``P1 = K1 [I | 0]``, ``P2 = K2 [R | t]`` (``cv2.triangulatePoints``). Returns the points
    ``(C, N, 3)`` (camera 1 frame) and ``(C, N)`` bool: finite with positive depth in both cameras
    (the cheirality test of H&Z section 9.6.3; what ``cheirality_counts`` counts, in pixels here).
    """
    candidates = np.asarray(candidates, dtype=np.float64)
    x = np.stack([np.asarray(x1, dtype=np.float64), np.asarray(x2, dtype=np.float64)])
    P1 = projection_matrix(K1, np.eye(3), np.zeros(3))
    points, in_front = [], []
    for candidate in candidates:
        P = np.stack([P1, projection_matrix(K2, candidate[:, :3], candidate[:, 3])])
        X = triangulate_dlt(P, x)
        finite = np.all(np.isfinite(X), axis=1)
        depth = point_depths(P, np.where(finite[:, None], X, 0.0))
        points.append(X)
        in_front.append(finite & (depth[0] > 0) & (depth[1] > 0))
    return np.array(points).reshape(len(candidates), -1, 3), np.array(in_front).reshape(len(candidates), -1)


def check_pixel(pixel: Any, width: int, height: int, image: int) -> np.ndarray:
    """``pixel`` as a finite ``(2,)`` array inside image ``image`` (pixel edges ``[-0.5, size - 0.5]``)."""
    try:
        uv = np.asarray(pixel, dtype=np.float64).reshape(2)
    except (TypeError, ValueError):
        raise InvalidValue("pixel", f"expected two numbers (u, v), got {pixel!r}") from None
    if not np.all(np.isfinite(uv)):
        raise InvalidValue("pixel", f"(u, v) must be finite numbers, got {tuple(uv)}")
    if not (-0.5 <= uv[0] <= width - 0.5 and -0.5 <= uv[1] <= height - 0.5):
        raise InvalidValue("pixel", f"({uv[0]:g}, {uv[1]:g}) is outside image {image} ({width}x{height}: u in "
                                    f"[-0.5, {width - 0.5:g}], v in [-0.5, {height - 0.5:g}])")
    return uv


def fundamental_from_pose(K1: np.ndarray, K2: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``F = K2^-T [t]_x R K1^-1`` ``(3, 3)``, unit Frobenius norm (H&Z result 9.9 and eq. 9.2)."""
    from lab.geometry.rotations import skew

    F = np.linalg.inv(K2).T @ skew(np.asarray(t, dtype=np.float64).reshape(3)) @ np.asarray(R) @ np.linalg.inv(K1)
    return F / np.linalg.norm(F)


# ----------------------------------------------------------------------------------------------------
# Which geometry is shown: the session's, else the ground truth
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TwoViewGeometry:
    """The two-view geometry the interactions draw, and where each part comes from.

    ``sizes`` are (width, height) of image 1 and image 2; ``K1``/``K2`` (3, 3), ``F`` (3, 3) and the pose
    ``R`` (3, 3), ``t`` (3,) of camera 2 (``X_2 = R X_1 + t``) are None when neither the session nor the
    truth has them. ``f_source`` / ``pose_source`` say where F and the pose come from ("" when unknown).
    """

    sizes: tuple[tuple[int, int], tuple[int, int]]
    K1: np.ndarray | None
    K2: np.ndarray | None
    F: np.ndarray | None
    R: np.ndarray | None
    t: np.ndarray | None
    f_source: str
    pose_source: str

    @property
    def has_pose(self) -> bool:
        return self.R is not None and self.K1 is not None and self.K2 is not None

    def camera(self, image: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(K, R, t)`` of camera ``image`` (1: the world frame; 2: at the pose), None when unknown."""
        if image == 1:
            return None if self.K1 is None else (self.K1, np.eye(3), np.zeros(3))
        if not self.has_pose:
            return None
        return self.K2, self.R, self.t

    def centres(self) -> np.ndarray:
        """Camera centres ``(2, 3)``: the origin and ``-R^T t``."""
        return np.stack([np.zeros(3), camera_centre(self.R, self.t)])


def _matrix_or_none(value: Any) -> np.ndarray | None:
    if value is None:
        return None
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (3, 3) or not np.all(np.isfinite(array)) or not np.any(array):
        return None
    return array


def two_view_geometry(state: Mapping[str, Any], truth: Mapping[str, Any]) -> TwoViewGeometry | None:
    """The geometry to draw: the session's F and pose when it has computed them, else the truth's.

    F: the state's ``F`` (the last written: RANSAC's, else the 8-point's), else the truth's; the pose:
    the refined ``R``, ``t``, else ``pose`` (``recover_pose``), else the truth's (in the truth's units,
    e.g. metres; the session's has ``|t| = 1``). K: the state's (the dataset's), else the truth's.
    None when ``images`` is not a pair.
    """
    images = state.get("images")
    if not isinstance(images, ImageSet) or len(images) != 2:
        return None
    sizes = ((images[0].width, images[0].height), (images[1].width, images[1].height))
    K1 = _matrix_or_none(state.get("K1"))
    K2 = _matrix_or_none(state.get("K2"))
    if K1 is None or K2 is None:
        K1, K2 = _matrix_or_none(truth.get("K1")), _matrix_or_none(truth.get("K2"))
    R = t = None
    pose_source = ""
    if state.get("R") is not None and state.get("t") is not None:
        R, t, pose_source = np.asarray(state["R"], float), np.asarray(state["t"], float), "the session (refine_pose)"
    elif state.get("pose") is not None:
        pose = np.asarray(state["pose"], dtype=np.float64)
        R, t, pose_source = pose[:, :3], pose[:, 3], "the session (recover_pose)"
    elif truth.get("R") is not None and truth.get("t") is not None and np.linalg.norm(truth["t"]) > 0:
        R, t, pose_source = np.asarray(truth["R"], float), np.asarray(truth["t"], float), "the ground truth"
    F = _matrix_or_none(state.get("F"))
    f_source = "the session (the last F written: RANSAC's, else the 8-point's)" if F is not None else ""
    if F is None and _matrix_or_none(truth.get("F")) is not None:
        F, f_source = np.asarray(truth["F"], dtype=np.float64), "the ground truth"
    if F is None and R is not None and K1 is not None and K2 is not None:
        F, f_source = fundamental_from_pose(K1, K2, R, t), f"the pose from {pose_source}"
    return TwoViewGeometry(sizes, K1, K2, F, R, t, f_source, pose_source)


def _observations(state: Mapping[str, Any], truth: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """Matched pixels to triangulate: the session's inliers (or matches), else the truth's exact pairs."""
    x1, x2 = state.get("x1"), state.get("x2")
    if x1 is not None and x2 is not None and len(x1) > 0 and len(x1) == len(x2):
        x1, x2 = np.asarray(x1, dtype=np.float64), np.asarray(x2, dtype=np.float64)
        inliers = state.get("inliers")
        if inliers is not None and np.shape(inliers) == (len(x1),) and np.any(inliers):
            x1, x2 = x1[np.asarray(inliers, bool)], x2[np.asarray(inliers, bool)]
        return x1, x2
    if truth.get("x1_exact") is not None and len(truth["x1_exact"]) > 0:
        return np.asarray(truth["x1_exact"], dtype=np.float64), np.asarray(truth["x2_exact"], dtype=np.float64)
    return None


def scene_depths(geometry: TwoViewGeometry, pairs: tuple[np.ndarray, np.ndarray] | None) -> tuple[float, float]:
    """A typical and a far depth in camera 1 (the median and 95th percentile of the triangulated pairs).

    Sizes the drawing: the image planes, the rays' length. In the pose's units (the session's
    baseline is 1); without a pose or pairs, 5 and 8 baselines.
    """
    baseline = float(np.linalg.norm(geometry.t)) if geometry.t is not None else 1.0
    baseline = baseline if baseline > 0 else 1.0
    if geometry.has_pose and pairs is not None and len(pairs[0]):
        step = max(1, len(pairs[0]) // 500)
        x1, x2 = pairs[0][::step], pairs[1][::step]
        P = np.stack([projection_matrix(geometry.K1, np.eye(3), np.zeros(3)),
                      projection_matrix(geometry.K2, geometry.R, geometry.t)])
        X = triangulate_dlt(P, np.stack([x1, x2]))
        finite = np.all(np.isfinite(X), axis=1)
        depth = point_depths(P, np.where(finite[:, None], X, 0.0))
        good = finite & (depth[0] > 0) & (depth[1] > 0)
        if good.sum() >= 3:
            z = depth[0][good]
            return float(np.median(z)), float(np.percentile(z, 95))
    return 5.0 * baseline, 8.0 * baseline


# ----------------------------------------------------------------------------------------------------
# Results of the explorer's actions
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PixelPick:
    """A pixel picked in image ``image`` (1 or 2) and what it determines.

    ``line`` ``(3,)`` is its epipolar line in the other image (``a^2 + b^2 = 1``), ``segment`` ``(2, 2)``
    that line clipped to the other image (None when it misses it); ``ray`` ``(2, 3)`` the ray from the
    camera's centre through the pixel to the far depth (None without K), ``plane`` ``(3, 3)`` the
    epipolar plane's triangle (both centres and the ray's far end; None without a pose).
    """

    image: int
    pixel: np.ndarray
    line: np.ndarray
    segment: np.ndarray | None
    ray: np.ndarray | None
    plane: np.ndarray | None


@dataclass(frozen=True)
class PointMove:
    """A 3D point (camera 1 frame) and its images: ``pixels`` ``(2, 2)`` and ``depths`` ``(2,)`` in image 1 and
    image 2, ``lines`` ``(2, 3)`` its epipolar lines in image 1 (``F^T x2``) and image 2 (``F x1``), with
    ``F`` the pose's, ``segments`` those lines clipped to each image, ``plane`` ``(4, 3)`` the epipolar quad."""

    point: np.ndarray
    pixels: np.ndarray
    depths: np.ndarray
    lines: np.ndarray
    segments: tuple[np.ndarray | None, np.ndarray | None]
    plane: np.ndarray


def _clipped(line: np.ndarray, width: int, height: int) -> np.ndarray | None:
    start, end, valid = clip_lines(line.reshape(1, 3), width, height)
    return np.stack([start[0], end[0]]) if valid[0] else None


def pick(geometry: TwoViewGeometry, pixel: Any, *, image: Literal[1, 2] = 1, far: float = 10.0) -> PixelPick:
    """What a pixel of image ``image`` determines: its epipolar line in the other image, its ray, the plane.

    The line is ``F x`` (a pixel of image 1) or ``F^T x`` (of image 2), from
    :func:`lab.modules.epipolar.epipolar_lines`; the ray runs from the camera centre to depth ``far``.
    Raises :class:`InvalidValue` for a pixel outside the image, :class:`MissingInput` without F.
    """
    if image not in (1, 2):
        raise InvalidValue("image", f"expected 1 or 2, got {image!r}")
    width, height = geometry.sizes[image - 1]
    uv = check_pixel(pixel, width, height, image)
    if geometry.F is None:
        raise MissingInput("F", "no fundamental matrix yet: run estimate_fundamental_8point or _ransac (this "
                                "dataset has no ground truth to show instead)")
    line = epipolar_lines(geometry.F, uv.reshape(1, 2), image=image)[0]
    other_width, other_height = geometry.sizes[2 - image]
    segment = _clipped(line, other_width, other_height)
    camera = geometry.camera(image)
    ray = plane = None
    if camera is not None:
        K, R, t = camera
        ray = np.stack([camera_centre(R, t), lift_pixels(K, R, t, uv.reshape(1, 2), far)[0]])
        if geometry.has_pose:
            plane = np.stack([geometry.centres()[0], geometry.centres()[1], ray[1]])
    return PixelPick(image, uv, line, segment, ray, plane)


def move(geometry: TwoViewGeometry, point: Any, *, extend: float = 1.25) -> PointMove:
    """Project a 3D point into both images; its epipolar lines (from the pose's F) and epipolar plane.

    Raises :class:`MissingInput` without a pose and K, :class:`InvalidValue` for a non-finite point,
    one on a camera plane, or one on the baseline.
    """
    if not geometry.has_pose:
        raise MissingInput("pose", "no relative pose yet: run recover_pose (this dataset has no ground truth "
                                   "pose to show instead)")
    try:
        X = np.asarray(point, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise InvalidValue("point", f"expected three numbers (x, y, z), got {point!r}") from None
    if not np.all(np.isfinite(X)):
        raise InvalidValue("point", f"(x, y, z) must be finite numbers, got {tuple(X)}")
    pixels, depths = [], []
    for image in (1, 2):
        K, R, t = geometry.camera(image)
        pixel, depth = project_point(K, R, t, X)
        pixels.append(pixel)
        depths.append(depth)
    plane = epipolar_plane_corners(*geometry.centres(), X, extend=extend)
    F = fundamental_from_pose(geometry.K1, geometry.K2, geometry.R, geometry.t)
    lines = np.stack([epipolar_lines(F, pixels[1].reshape(1, 2), image=2)[0],
                      epipolar_lines(F, pixels[0].reshape(1, 2), image=1)[0]])
    segments = (_clipped(lines[0], *geometry.sizes[0]), _clipped(lines[1], *geometry.sizes[1]))
    return PointMove(X, np.stack(pixels), np.array(depths), lines, segments, plane)


# ----------------------------------------------------------------------------------------------------
# Drawing helpers (no viser)
# ----------------------------------------------------------------------------------------------------
def _unit_color(rgb: tuple[int, int, int], count: int = 1) -> np.ndarray:
    return np.tile(np.asarray(rgb, dtype=np.float64) / 255.0, (count, 1))


def explorer_overlays(geometry: TwoViewGeometry, picked: PixelPick | None,
                      moved: PointMove | None) -> tuple[list[Any], list[Any]]:
    """The 2D overlays (Points2D / Segments2D, ``view`` None) of image 1 and image 2: the picked pixel and its
    line, the moved point's projections and lines, and the epipoles inside the images."""
    overlays: tuple[list[Any], list[Any]] = ([], [])
    if geometry.F is not None:
        pair = epipoles(geometry.F)
        for index in (0, 1):
            if abs(pair[index, 2]) > 1e-12:
                xy = pair[index, :2] / pair[index, 2]
                width, height = geometry.sizes[index]
                if -0.5 <= xy[0] <= width - 0.5 and -0.5 <= xy[1] <= height - 0.5:
                    overlays[index].append(Points2D(xy.reshape(1, 2), colors=np.ones((1, 3))))
    if picked is not None:
        overlays[picked.image - 1].append(Points2D(picked.pixel.reshape(1, 2), colors=_unit_color(PICK_COLOR)))
        if picked.segment is not None:
            overlays[2 - picked.image].append(Segments2D(picked.segment[:1], picked.segment[1:],
                                                         colors=_unit_color(PICK_COLOR)))
    if moved is not None:
        for index in (0, 1):
            if moved.depths[index] > 0:
                overlays[index].append(Points2D(moved.pixels[index].reshape(1, 2), colors=_unit_color(POINT_COLOR)))
            segment = moved.segments[index]
            if segment is not None:
                overlays[index].append(Segments2D(segment[:1], segment[1:], colors=_unit_color(POINT_COLOR)))
    return overlays


def draw_overlays(image: Image, overlays: list[Any], *, max_side: int | None = None, min_side: int | None = None,
                  thickness: int = 2, base: np.ndarray | None = None) -> np.ndarray:
    """``image`` with ``overlays`` (Points2D / Segments2D, ``view`` None) drawn thick, ``(H', W', 3)`` uint8.

    The size is :func:`lab.viewer.renderers.overlay_view`'s (shrunk to ``max_side`` or enlarged to
    ``min_side``); points are discs' outlines and segments lines ``thickness`` pixels wide, so that a
    single epipolar line stays visible on a scene plane or a panel image. ``base``: that resized
    image already made (``overlay_view(image, [], ...)``, kept by the caller: a click redraws fast).
    """
    rgb = (overlay_view(image, [], max_side=max_side, min_side=min_side) if base is None else base).copy()
    scale_x, scale_y = rgb.shape[1] / image.width, rgb.shape[0] / image.height
    shift = 4
    one = 1 << shift

    def fixed(xy: np.ndarray) -> tuple[int, int]:
        return (int(round(((xy[0] + 0.5) * scale_x - 0.5) * one)), int(round(((xy[1] + 0.5) * scale_y - 0.5) * one)))

    radius = int(round(max(4.0, min(rgb.shape[:2]) / 60.0) * one))
    for overlay in overlays:
        colors = overlay.colors if overlay.colors is not None else np.ones((len(overlay), 3))
        for i in range(len(overlay)):
            color = tuple(int(c) for c in np.clip(colors[i], 0, 1) * 255 + 0.5)
            if isinstance(overlay, Segments2D):
                cv2.line(rgb, fixed(overlay.start[i]), fixed(overlay.end[i]), color, thickness, cv2.LINE_AA, shift)
            else:
                cv2.circle(rgb, fixed(overlay.xy[i]), radius, color, thickness, cv2.LINE_AA, shift)
    return rgb


def match_pair_image(image1: Image, image2: Image, x1: np.ndarray, x2: np.ndarray, inliers: np.ndarray | None, *,
                     height: int = 360, max_lines: int = MAX_MATCH_LINES) -> np.ndarray:
    """The two images side by side ``(height, W1' + W2', 3)`` uint8, each match joined by a line: inliers green,
    outliers red, all matches yellow when ``inliers`` is None (RANSAC has not run).

    Both images are scaled to ``height`` (pixel centres stay centres); at most ``max_lines`` matches
    are joined (evenly spread over the list, outliers and inliers alike), every match gets its two dots.
    """
    halves, scales = [], []
    for image in (image1, image2):
        rgb = to_rgb8(image.pixels)
        scale = height / rgb.shape[0]
        size = (max(1, round(rgb.shape[1] * scale)), height)
        halves.append(cv2.resize(rgb, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR))
        scales.append((size[0] / rgb.shape[1], height / rgb.shape[0]))
    canvas = np.ascontiguousarray(np.concatenate(halves, axis=1))
    offset = halves[0].shape[1]
    shift = 4
    one = 1 << shift

    def fixed(xy: np.ndarray, index: int, dx: float) -> np.ndarray:
        sx, sy = scales[index]
        out = np.column_stack([(xy[:, 0] + 0.5) * sx - 0.5 + dx, (xy[:, 1] + 0.5) * sy - 0.5])
        return np.round(out * one).astype(np.int64)

    x1 = np.asarray(x1, dtype=np.float64).reshape(-1, 2)
    x2 = np.asarray(x2, dtype=np.float64).reshape(-1, 2)
    a, b = fixed(x1, 0, 0.0), fixed(x2, 1, float(offset))
    if inliers is None:
        colors = [UNCLASSIFIED_COLOR] * len(x1)
    else:
        colors = [INLIER_COLOR if keep else OUTLIER_COLOR for keep in np.asarray(inliers, dtype=bool)]
    joined = np.unique(np.linspace(0, len(x1) - 1, min(len(x1), max_lines)).round().astype(int)) if len(x1) else []
    for i in joined:
        cv2.line(canvas, tuple(int(v) for v in a[i]), tuple(int(v) for v in b[i]), colors[i], 1, cv2.LINE_AA, shift)
    radius = int(round(2.5 * one))
    for i in range(len(x1)):
        cv2.circle(canvas, tuple(int(v) for v in a[i]), radius, colors[i], -1, cv2.LINE_AA, shift)
        cv2.circle(canvas, tuple(int(v) for v in b[i]), radius, colors[i], -1, cv2.LINE_AA, shift)
    return canvas


def _wxyz(rotation: np.ndarray) -> np.ndarray:
    import viser.transforms as vtf

    return np.asarray(vtf.SO3.from_matrix(rotation).wxyz, dtype=np.float64)


def _frustum_segments(centre: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Line segments ``(8, 2, 3)`` of a frustum: centre to each corner, and the image's outline."""
    spokes = np.stack([np.repeat(centre[None], 4, axis=0), corners], axis=1)
    outline = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
    return np.concatenate([spokes, outline]).astype(np.float32)


# ----------------------------------------------------------------------------------------------------
# Interaction 1: click a pixel, drag a point
# ----------------------------------------------------------------------------------------------------
class EpipolarExplorer(Interaction):
    """Click a pixel (in the 3D scene's image planes, or by number) to see its epipolar line and ray; drag a
    3D point to see its projections, its epipolar plane and both of its lines move."""

    title = "Epipolar explorer: click a pixel, drag a point"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        self.lock = threading.RLock()
        self.nodes = NamedHandles()
        self.geometry: TwoViewGeometry | None = None
        self.images: ImageSet | None = None
        self.depth = 1.0  # depth of the image planes drawn in the frustums
        self.far = 8.0
        self.typical = 5.0
        self.last_pick: PixelPick | None = None
        self.last_point: PointMove | None = None
        self.textures: list[np.ndarray | None] = [None, None]  # what the image planes / panel images show
        self._key: tuple | None = None
        self._syncing = False
        self._handle: Any = None
        self._bases: dict[tuple[int, int, str], np.ndarray] = {}
        gui = ctx.gui
        self.source_md = self.track(gui.add_markdown("Open a two-image session."))
        self.image_choice = self.track(gui.add_dropdown("pixel in", ("image 1", "image 2"), initial_value="image 1",
                                                        hint="which image the pixel (u, v) is in"))
        self.pixel_input = self.track(gui.add_vector2("pixel (u, v)", (0.0, 0.0), step=1.0,
                                                      hint="a pixel: its epipolar line in the other image and "
                                                           "its ray in 3D (or click an image plane in the scene)"))
        self.pick_button = self.track(gui.add_button("Show epipolar line", hint="use the pixel above"))
        self.pick_md = self.track(gui.add_markdown(""))
        self.point_input = self.track(gui.add_vector3("3D point (x, y, z)", (0.0, 0.0, 5.0), step=0.01,
                                                      hint="a point in camera 1's frame (or drag the gizmo)"))
        self.point_md = self.track(gui.add_markdown(""))
        with ctx.images:
            self.panel_folder = self.track(gui.add_folder("Epipolar explorer", order=1000.0))
            with self.panel_folder:
                self.panel_images = [self.track(gui.add_image(np.zeros((8, 8, 3), np.uint8), label=f"image {i}",
                                                              format="jpeg")) for i in (1, 2)]
        self.pick_button.on_click(lambda _: ctx.guarded(self._pick_from_inputs)())
        self.pixel_input.on_update(lambda _: None if self._syncing else ctx.guarded(self._pick_from_inputs)())
        self.point_input.on_update(lambda _: None if self._syncing else
                                   ctx.guarded(lambda: self._move(self.point_input.value, from_handle=False))())

    # --- public actions (what a click, a drag or a test does) --------------------------------------
    def pick_pixel(self, u: float, v: float, *, image: Literal[1, 2] = 1) -> PixelPick | None:
        """Show the epipolar line and ray of pixel ``(u, v)`` of image ``image``; None (error shown) when invalid."""
        return self._safely(lambda: self._pick((u, v), image))

    def click_image(self, image: Literal[1, 2], ray_origin: Any, ray_direction: Any) -> PixelPick | None:
        """A click on the image plane of camera ``image`` (its ray in world coordinates): pick that pixel."""
        return self._safely(lambda: self._click(image, ray_origin, ray_direction))

    def move_point(self, xyz: Any) -> PointMove | None:
        """Move the 3D point to ``xyz`` (camera 1 frame); None (error shown) when invalid."""
        return self._safely(lambda: self._move(xyz, from_handle=False))

    def scene_nodes(self) -> list[str]:
        """Names of the scene nodes drawn now."""
        with self.lock:
            return self.nodes.names()

    def bounds(self) -> np.ndarray | None:
        """``(2, 3)`` min and max corner of what the explorer draws (both cameras, the ray, the point), or None:
        for framing the tab's camera before the session has 3D values of its own."""
        with self.lock:
            if self.geometry is None or self.geometry.camera(1) is None:
                return None
            points = [np.zeros((1, 3)), lift_pixels(*self.geometry.camera(1), np.array(
                [[0.0, 0.0], self.geometry.sizes[0]], dtype=np.float64), self.typical)]
            if self.geometry.has_pose:
                points.append(self.geometry.centres())
            if self.last_point is not None:
                points.append(self.last_point.point.reshape(1, 3))
            points = np.concatenate(points)
            return np.stack([points.min(axis=0), points.max(axis=0)])

    # --- viser wiring -------------------------------------------------------------------------------
    def _safely(self, action: Callable[[], Any]) -> Any:
        """Run ``action``; what it raises is shown in the tab (as a viser callback's error would be)."""
        result: list[Any] = [None]

        def run() -> None:
            result[0] = action()

        self.ctx.guarded(run)()
        return result[0]

    def _pick_from_inputs(self) -> None:
        image = 2 if self.image_choice.value == "image 2" else 1
        self._pick(self.pixel_input.value, image)

    def _click(self, image: int, ray_origin: Any, ray_direction: Any) -> PixelPick:
        with self.lock:
            geometry = self._require_geometry()
            camera = geometry.camera(image)
            if camera is None:
                raise MissingInput("K1" if image == 1 else "pose", f"camera {image} is not placed in the scene")
            pixel = click_to_pixel(ray_origin, ray_direction, *camera, self.depth)
            return self._pick(pixel, image)

    def _require_geometry(self) -> TwoViewGeometry:
        if self.geometry is None:
            raise MissingInput("images", "the session has no pair of images")
        return self.geometry

    def _pick(self, pixel: Any, image: int) -> PixelPick:
        with self.lock:
            result = pick(self._require_geometry(), pixel, image=image, far=self.far)
            self.last_pick = result
            self._sync_inputs(pixel=result.pixel, image=image)
            self._draw_pick()
            self._draw_textures()
            return result

    def _move(self, xyz: Any, *, from_handle: bool, panels: bool = True) -> PointMove:
        """Move the point; ``panels`` False (while the gizmo is dragged) redraws only the scene's image planes."""
        with self.lock:
            result = move(self._require_geometry(), xyz)
            self.last_point = result
            self._sync_inputs(point=result.point)
            if not from_handle and self._handle is not None:
                self._handle.position = tuple(float(v) for v in result.point)
            self._draw_point()
            self._draw_textures(panels=panels)
            return result

    def _sync_inputs(self, *, pixel: np.ndarray | None = None, image: int | None = None,
                     point: np.ndarray | None = None) -> None:
        self._syncing = True
        try:
            if pixel is not None:
                self.pixel_input.value = (float(pixel[0]), float(pixel[1]))
            if image is not None:
                self.image_choice.value = f"image {image}"
            if point is not None:
                self.point_input.value = tuple(float(v) for v in point)
        finally:
            self._syncing = False

    # --- redraw on new state --------------------------------------------------------------------------
    def update(self, state: Mapping[str, Any]) -> None:
        truth = self.ctx.session.truth
        key = tuple(id(state.get(name)) for name in ("images", "K1", "K2", "F", "R", "t", "pose", "x1", "inliers"))
        with self.lock:
            if key == self._key:
                return
            self._key = key
            self.geometry = two_view_geometry(state, truth)
            self.images = state.get("images") if self.geometry is not None else None
            self.nodes.clear()
            self._handle = None
            if self.geometry is None:
                self.last_pick = self.last_point = None
                self.source_md.content = "This session has no pair of images."
                return
            self.typical, self.far = scene_depths(self.geometry, _observations(state, truth))
            baseline = float(np.linalg.norm(self.geometry.t)) if self.geometry.has_pose else self.typical / 5.0
            self.depth = max(min(0.35 * baseline, 0.25 * self.typical), 1e-3 * self.typical)
            self.source_md.content = self._sources()
            self._draw_rig()
            # redo the last pick and point with the new geometry (drop them when no longer possible)
            for redo in (self._redo_pick, self._redo_point):
                try:
                    redo()
                except LabError:
                    pass
            self._draw_textures()

    def _redo_pick(self) -> None:
        old, self.last_pick = self.last_pick, None
        self.pick_md.content = ""
        if old is not None:
            self.last_pick = pick(self.geometry, old.pixel, image=old.image, far=self.far)
            self._draw_pick()

    def _redo_point(self) -> None:
        old, self.last_point = self.last_point, None
        self.point_md.content = ""
        if not self.geometry.has_pose:
            return
        start = old.point if old is not None else lift_pixels(
            self.geometry.K1, np.eye(3), np.zeros(3),
            np.array([[(self.geometry.sizes[0][0] - 1) / 2, (self.geometry.sizes[0][1] - 1) / 2]]), self.typical)[0]
        self.last_point = move(self.geometry, start)
        self._sync_inputs(point=self.last_point.point)
        self._add_handle(self.last_point.point)
        self._draw_point()

    def _sources(self) -> str:
        g = self.geometry
        lines = [f"**F** from {g.f_source}." if g.F is not None else
                 "**F**: none yet (run the 8-point or RANSAC step; this dataset has no ground truth).",
                 f"**Pose** from {g.pose_source}" + (" (units of the truth)." if g.pose_source == "the ground truth"
                                                      else " (baseline = 1).") if g.R is not None else
                 "**Pose**: none yet (run recover_pose): no camera 2 in 3D.",
                 "Click an image plane in the scene (camera 1 or 2) or type a pixel; drag the gizmo to move the "
                 "3D point."]
        if g.K1 is None:
            lines.append("No K: the rays cannot be drawn in 3D.")
        return "  \n".join(lines)

    # --- scene drawing -------------------------------------------------------------------------------------
    def _draw_rig(self) -> None:
        """Both cameras: a frustum and the image as a clickable plane at ``self.depth``."""
        scene, ctx = self.ctx.scene, self.ctx
        for image in (1, 2):
            camera = self.geometry.camera(image)
            if camera is None:
                continue
            width, height = self.geometry.sizes[image - 1]
            placement = image_placement(*camera, width, height, self.depth)
            centre = camera_centre(camera[1], camera[2])
            self.nodes.put(f"rig/camera{image}/frustum", lambda: scene.add_line_segments(
                ctx.node("rig", f"camera{image}", "frustum"), points=_frustum_segments(centre, placement.corners),
                colors=CAMERA_COLORS[image - 1], thickness=2.0, thickness_units="screen"))
            self.nodes.put(f"rig/camera{image}/label", lambda: scene.add_label(
                ctx.node("rig", f"camera{image}", "label"), f"camera {image}", position=tuple(centre)))

    def _image_plane(self, image: int, texture: np.ndarray) -> None:
        camera = self.geometry.camera(image)
        if camera is None:
            return
        width, height = self.geometry.sizes[image - 1]
        placement = image_placement(*camera, width, height, self.depth)
        name = f"rig/camera{image}/image"
        handle = self.nodes.handles.get(name)
        if handle is not None:
            handle.image = texture
            return
        handle = self.nodes.put(name, lambda: self.ctx.scene.add_image(
            self.ctx.node("rig", f"camera{image}", "image"), texture, placement.render_width, placement.render_height,
            format="jpeg", jpeg_quality=85, wxyz=_wxyz(placement.rotation), position=placement.position,
            cast_shadow=False, receive_shadow=False))
        handle.on_click(lambda event, image=image: self.ctx.guarded(
            lambda: self._click(image, event.ray_origin, event.ray_direction))())

    def _draw_textures(self, *, panels: bool = True) -> None:
        """Both images with the current overlays: on the image planes in 3D and (``panels``) in the Images panel."""
        if self.geometry is None or self.images is None:
            return
        overlays = explorer_overlays(self.geometry, self.last_pick, self.last_point)
        for index in (0, 1):
            image = self.images[index]
            self.textures[index] = draw_overlays(image, overlays[index], base=self._base(index, "plane"))
            self._image_plane(index + 1, self.textures[index])
            if not panels:
                continue
            panel = draw_overlays(image, overlays[index], base=self._base(index, "panel"))
            self.panel_images[index].image = panel
            self.panel_images[index].label = f"image {index + 1}: " + ", ".join(
                ["yellow: picked pixel / its epipolar line"] * (self.last_pick is not None)
                + ["magenta: the 3D point's projection and epipolar line"] * (self.last_point is not None)
                + ["white: epipole"])

    def _base(self, index: int, kind: Literal["plane", "panel"]) -> np.ndarray:
        """Image ``index`` resized for a scene plane or the panel, without overlays (made once per image set)."""
        key = (id(self.images), index, kind)
        if key not in self._bases:
            sides = {"plane": (FRUSTUM_MAX_SIDE, None), "panel": (PANEL_MAX_SIDE, PANEL_MIN_SIDE)}[kind]
            self._bases = {k: v for k, v in self._bases.items() if k[0] == id(self.images)}
            self._bases[key] = overlay_view(self.images[index], [], max_side=sides[0], min_side=sides[1])
        return self._bases[key]

    def _segments(self, name: str, points: np.ndarray, color: tuple[int, int, int]) -> None:
        self.nodes.put(name, lambda: self.ctx.scene.add_line_segments(
            self.ctx.node(*name.split("/")), points=np.asarray(points, dtype=np.float32).reshape(-1, 2, 3),
            colors=color, thickness=3.0, thickness_units="screen"))

    def _mesh(self, name: str, vertices: np.ndarray, faces: np.ndarray, color: tuple[int, int, int]) -> None:
        self.nodes.put(name, lambda: self.ctx.scene.add_mesh_simple(
            self.ctx.node(*name.split("/")), np.asarray(vertices, dtype=np.float32), np.asarray(faces, dtype=np.uint32),
            color=color, opacity=0.35, side="double", cast_shadow=False, receive_shadow=False))

    def _lifted(self, image: int, segment: np.ndarray | None) -> np.ndarray | None:
        """A 2D segment of image ``image`` on its plane in 3D, ``(1, 2, 3)`` (just in front of the texture)."""
        camera = self.geometry.camera(image)
        if camera is None or segment is None:
            return None
        return lift_pixels(*camera, segment, 0.995 * self.depth).reshape(1, 2, 3)

    def _draw_pick(self) -> None:
        self.nodes.drop("pick")
        result = self.last_pick
        if result is None:
            return
        marker = None
        if result.ray is not None:
            self._segments("pick/ray", result.ray, PICK_COLOR)
            camera = self.geometry.camera(result.image)
            marker = lift_pixels(*camera, result.pixel.reshape(1, 2), self.depth)[0]
            self.nodes.put("pick/pixel", lambda: self.ctx.scene.add_icosphere(
                self.ctx.node("pick", "pixel"), radius=0.02 * self.depth, color=PICK_COLOR, position=tuple(marker)))
        if result.plane is not None:
            self._mesh("pick/plane", result.plane, np.array([[0, 1, 2]]), PICK_COLOR)
            self._segments("pick/baseline", result.plane[:2], (80, 80, 80))
        lifted = self._lifted(3 - result.image, result.segment)
        if lifted is not None:
            self._segments("pick/line", lifted, PICK_COLOR)
        text = [f"Pixel ({result.pixel[0]:.1f}, {result.pixel[1]:.1f}) of image {result.image} → epipolar line "
                f"{result.line[0]:.4f} u {result.line[1]:+.4f} v {result.line[2]:+.1f} = 0 in image {3 - result.image}"
                + ("" if result.segment is not None else " (it misses the image)") + "."]
        if result.ray is not None:
            direction = (result.ray[1] - result.ray[0]) / np.linalg.norm(result.ray[1] - result.ray[0])
            text.append(f"Its ray leaves camera {result.image}'s centre along "
                        f"({', '.join(f'{v:.3f}' for v in direction)});"
                        + (" the epipolar plane (yellow) holds it and both centres, and cuts image "
                           f"{3 - result.image} along the line." if result.plane is not None else ""))
        self.pick_md.content = "  \n".join(text)

    def _add_handle(self, point: np.ndarray) -> None:
        handle = self.nodes.put("point/handle", lambda: self.ctx.scene.add_transform_controls(
            self.ctx.node("point", "handle"), scale=max(0.15 * self.typical, 1e-3), disable_rotations=True,
            depth_test=False, position=tuple(float(v) for v in point)))
        self._handle = handle

        def dragged(event: Any) -> None:  # the panel images wait for the end of the drag
            self._move(np.asarray(event.target.position, dtype=np.float64), from_handle=True,
                       panels=getattr(event, "phase", "end") != "update")

        handle.on_update(lambda event: self.ctx.guarded(dragged)(event))

    def _draw_point(self) -> None:
        for name in [n for n in self.nodes.names() if n.startswith("point/") and n != "point/handle"]:
            self.nodes.drop_exact(name)
        result = self.last_point
        if result is None:
            return
        c1, c2 = self.geometry.centres()
        X = result.point
        self._segments("point/rays", np.array([[c1, X], [c2, X]]), POINT_COLOR)
        self._mesh("point/plane", result.plane, np.array([[0, 1, 2], [0, 2, 3]]), POINT_COLOR)
        self._segments("point/baseline", np.array([[c1, c2]]), (80, 80, 80))
        self.nodes.put("point/marker", lambda: self.ctx.scene.add_icosphere(
            self.ctx.node("point", "marker"), radius=0.015 * self.far, color=POINT_COLOR, position=tuple(X)))
        for image in (1, 2):
            lifted = self._lifted(image, result.segments[image - 1])
            if lifted is not None:
                self._segments(f"point/line{image}", lifted, POINT_COLOR)
        rows = []
        for index in (0, 1):
            where = "behind the camera!" if result.depths[index] <= 0 else f"depth {result.depths[index]:.3g}"
            rows.append(f"image {index + 1}: ({result.pixels[index, 0]:.1f}, {result.pixels[index, 1]:.1f}), {where}")
        self.point_md.content = ("Point (" + ", ".join(f"{v:.3g}" for v in X) + ") projects to  \n" + "  \n".join(rows)
                                 + "  \nIts epipolar plane (magenta) holds both centres; it cuts each image along "
                                   "the point's epipolar line, through the projection and the epipole.")

    def close(self) -> None:
        with self.lock:
            self.nodes.clear()
            self._handle = None
        super().close()


# ----------------------------------------------------------------------------------------------------
# Interaction 2: the four pose candidates side by side
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CandidateAnalysis:
    """The four candidates of E and their cheirality test.

    ``candidates`` ``(4, 3, 4)``; ``counts`` ``(4,)`` points in front of both cameras (of ``total``);
    ``chosen`` the candidate with the most (what ``recover_pose`` keeps); ``points`` ``(4, N, 3)`` and
    ``in_front`` ``(4, N)`` the triangulated pairs drawn (candidate units: ``|t| = 1``); ``far`` the
    95th-percentile depth of the chosen candidate's points; each copy is drawn ``scale`` times its size,
    shifted by ``offsets`` ``(4, 3)``; ``source`` says where E / the candidates come from.
    """

    candidates: np.ndarray
    counts: np.ndarray
    chosen: int
    total: int
    points: np.ndarray
    in_front: np.ndarray
    far: float
    scale: float
    offsets: np.ndarray
    source: str


CANDIDATE_NAMES = ("(R1, t)", "(R2, t)", "(R1, -t)", "(R2, -t)")


def analyse_candidates(candidates: np.ndarray, K1: np.ndarray, K2: np.ndarray, x1: np.ndarray, x2: np.ndarray, *,
                       size: float | None = None, source: str = "") -> CandidateAnalysis:
    """Test and triangulate each candidate pose, and lay small copies of the rig out side by side.

    ``counts`` are :func:`lab.modules.epipolar.cheirality_counts` of the normalized pairs ``K^-1 x``
    (exactly what ``recover_pose`` compares), ``chosen`` their argmax. At most
    :data:`MAX_CANDIDATE_POINTS` pairs are triangulated for drawing (:func:`candidate_points`). Each
    copy is scaled so that the chosen candidate's far depth is ``size`` in the scene (default: its own
    size), and the copies go along x every ``1.6 size`` from ``1.4`` spacings on
    (:func:`candidate_layout`), beside the scene and apart from each other.
    """
    candidates = np.asarray(candidates, dtype=np.float64)
    if candidates.ndim != 3 or candidates.shape[1:] != (3, 4):
        raise InvalidValue("candidates", f"expected (C, 3, 4) stacked [R | t], got {candidates.shape}")
    x1 = np.asarray(x1, dtype=np.float64).reshape(-1, 2)
    x2 = np.asarray(x2, dtype=np.float64).reshape(-1, 2)
    if len(x1) == 0 or len(x1) != len(x2):
        raise MissingInput("x1", f"no matched pairs to test the candidates with ({len(x1)} and {len(x2)} points)")
    counts = cheirality_counts(candidates, pixels_to_normalized(x1, K1), pixels_to_normalized(x2, K2))
    chosen = int(np.argmax(counts))
    step = max(1, len(x1) // MAX_CANDIDATE_POINTS)
    points, in_front = candidate_points(candidates, K1, K2, x1[::step], x2[::step])
    depth = points[chosen][in_front[chosen], 2]
    baseline = float(np.linalg.norm(candidates[chosen][:, 3])) or 1.0
    far = float(np.percentile(depth, 95)) if len(depth) >= 3 else 8.0 * baseline
    size = far if size is None else float(size)
    offsets = candidate_layout(len(candidates), 1.6 * size, first=1.4)
    return CandidateAnalysis(candidates, counts, chosen, len(x1), points, in_front, far, size / far, offsets, source)


class PoseCandidates(Interaction):
    """The four ``[R | t]`` of E drawn side by side, each with the points it triangulates; the one with the
    points in front of both cameras (cheirality) highlighted."""

    title = "The four pose candidates of E"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        self.lock = threading.RLock()
        self.nodes = NamedHandles()
        self.analysis: CandidateAnalysis | None = None
        self._key: tuple | None = None
        self._state: Mapping[str, Any] = {}
        self.show_box = self.track(ctx.gui.add_checkbox("show in 3D", True, hint="draw the four rigs in the scene"))
        self.table_md = self.track(ctx.gui.add_markdown(""))
        self.show_box.on_update(lambda _: ctx.guarded(self._redraw)())

    def update(self, state: Mapping[str, Any]) -> None:
        key = tuple(id(state.get(n)) for n in ("candidates", "E", "K1", "K2", "x1", "inliers", "pose", "R"))
        with self.lock:
            if key == self._key:
                return
            self._key = key
            self._state = state
            try:
                self.analysis = self._analyse(state, self.ctx.session.truth)
            except LabError as exc:
                self.analysis = None
                self.table_md.content = f"{exc.reason}"
            self._redraw()

    def _analyse(self, state: Mapping[str, Any], truth: Mapping[str, Any]) -> CandidateAnalysis | None:
        geometry = two_view_geometry(state, truth)
        if state.get("candidates") is not None:
            candidates, source = np.asarray(state["candidates"]), "the session (decompose_essential)"
        elif _matrix_or_none(truth.get("E")) is not None:
            candidates, source = essential_candidates(truth["E"]), "the ground truth E"
        else:
            raise MissingInput("candidates", "No candidates yet: run decompose_essential (this dataset has no ground "
                                             "truth E to show instead).")
        if geometry is None or geometry.K1 is None or geometry.K2 is None:
            raise MissingInput("K1", "No K: the candidates cannot be tested.")
        pairs = _observations(state, truth)
        if pairs is None:
            raise MissingInput("x1", "No matches to triangulate yet: run match_features.")
        _, far = scene_depths(geometry, pairs)  # in the units of the scene drawn (the explorer's)
        return analyse_candidates(candidates, geometry.K1, geometry.K2, *pairs, size=0.35 * far, source=source)

    def _redraw(self) -> None:
        with self.lock:
            self.nodes.clear()
            a = self.analysis
            if a is None:
                return
            self.table_md.content = self._table(a)
            if self.show_box.value:
                self._draw(a)

    def _table(self, a: CandidateAnalysis) -> str:
        rows = ["| # | candidate | in front of both | |", "|---|---|---|---|"]
        for i, count in enumerate(a.counts):
            mark = "**✓ passes (chosen)**" if i == a.chosen else ""
            rows.append(f"| {i + 1} | {CANDIDATE_NAMES[i] if i < 4 else i} | {int(count)} / {a.total} | {mark} |")
        pose = self._state.get("pose")
        note = ""
        if pose is not None:
            same = np.allclose(np.asarray(pose), a.candidates[a.chosen], atol=1e-9)
            note = "  \nThe chosen candidate is " + ("" if same else "**not** ") + "the pose recover_pose returned."
        return (f"Candidates from {a.source}; points: the session's inliers (or the truth's exact pairs). Drawn "
                "beside the scene along x: green rig = passes, blue points in front of both cameras, red "
                "behind one.\n\n" + "\n".join(rows) + note)

    def _draw(self, a: CandidateAnalysis) -> None:
        scene, ctx = self.ctx.scene, self.ctx
        spacing = 1.6 * a.far * a.scale
        size = 0.06 * spacing
        radius = 1.15 * a.far  # points farther than this from camera 1 are not drawn (candidate units)
        for i, (candidate, offset) in enumerate(zip(a.candidates, a.offsets)):
            color = CHOSEN_COLOR if i == a.chosen else OTHER_COLOR
            centres = a.scale * np.stack([np.zeros(3), camera_centre(candidate[:, :3], candidate[:, 3])])
            axes = [np.eye(3), candidate[:, :3].T]  # camera to world
            segments = []
            for centre, rotation in zip(centres, axes):
                corners = centre + (np.array([[-1, -0.75, 1.5], [1, -0.75, 1.5], [1, 0.75, 1.5], [-1, 0.75, 1.5]])
                                    * size) @ rotation.T
                segments.append(_frustum_segments(centre, corners))
            segments.append(np.array([[centres[0], centres[1]]], dtype=np.float32))
            rig = np.concatenate(segments) + offset.astype(np.float32)
            base = f"candidates/{i}"
            self.nodes.put(f"{base}/rig", lambda rig=rig, i=i, color=color: scene.add_line_segments(
                ctx.node("candidates", str(i), "rig"), points=rig, colors=color,
                thickness=4.0 if i == a.chosen else 2.0, thickness_units="screen"))
            X, front = a.points[i], a.in_front[i]
            shown = np.all(np.isfinite(X), axis=1) & (np.linalg.norm(X, axis=1) <= radius)
            if shown.any():
                colors = np.where(front[shown, None], np.array(IN_FRONT_COLOR), np.array(BEHIND_COLOR)).astype(np.uint8)
                points = (a.scale * X[shown] + offset).astype(np.float32)
                self.nodes.put(f"{base}/points", lambda points=points, colors=colors, i=i: scene.add_point_cloud(
                    ctx.node("candidates", str(i), "points"), points=points, colors=colors,
                    point_size=0.01 * spacing, point_shape="circle"))
            text = (f"#{i + 1} {CANDIDATE_NAMES[i] if i < 4 else ''}: {int(a.counts[i])}/{a.total} in front"
                    + (" ✓ passes" if i == a.chosen else ""))
            above = tuple(offset + np.array([0.0, -0.3 * spacing, 0.0]))  # up is -y
            self.nodes.put(f"{base}/label", lambda text=text, above=above, i=i: scene.add_label(
                ctx.node("candidates", str(i), "label"), text, position=above))

    def scene_nodes(self) -> list[str]:
        with self.lock:
            return self.nodes.names()

    def close(self) -> None:
        with self.lock:
            self.nodes.clear()
        super().close()


# ----------------------------------------------------------------------------------------------------
# Interaction 3: inliers and outliers on the image pair
# ----------------------------------------------------------------------------------------------------
class MatchColours(Interaction):
    """The matches drawn across the image pair: RANSAC's inliers green, its outliers red."""

    title = "Matches: inliers and outliers"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        self.lock = threading.RLock()
        self._key: tuple | None = None
        self.picture: np.ndarray | None = None
        self.counts: tuple[int, int] | None = None  # (inliers, outliers); None before RANSAC
        self.summary_md = self.track(ctx.gui.add_markdown(""))
        with ctx.images:
            self.panel = self.track(ctx.gui.add_image(np.zeros((8, 8, 3), np.uint8), label="matches", format="jpeg",
                                                      order=1001.0, visible=False))

    def update(self, state: Mapping[str, Any]) -> None:
        key = tuple(id(state.get(n)) for n in ("images", "x1", "x2", "inliers"))
        with self.lock:
            if key == self._key:
                return
            self._key = key
            images, x1, x2 = state.get("images"), state.get("x1"), state.get("x2")
            if not isinstance(images, ImageSet) or len(images) != 2 or x1 is None or x2 is None or len(x1) != len(x2):
                self.picture, self.counts = None, None
                self.panel.visible = False
                self.summary_md.content = "No matches yet: run match_features."
                return
            inliers = state.get("inliers")
            if inliers is not None and np.shape(inliers) != (len(x1),):
                inliers = None
            self.picture = match_pair_image(images[0], images[1], x1, x2, inliers)
            self.panel.image = self.picture
            self.panel.visible = True
            if inliers is None:
                self.counts = None
                self.panel.label = f"{len(x1)} matches (yellow: RANSAC has not classified them yet)"
                self.summary_md.content = (f"{len(x1)} matches, drawn in yellow in the Images panel; run "
                                           "estimate_fundamental_ransac to see its inliers (green) and outliers (red).")
                return
            inliers = np.asarray(inliers, dtype=bool)
            self.counts = (int(inliers.sum()), int((~inliers).sum()))
            self.panel.label = f"matches: {self.counts[0]} inliers (green), {self.counts[1]} outliers (red)"
            text = f"RANSAC kept {self.counts[0]} of {len(x1)} matches (green), rejected {self.counts[1]} (red)."
            truth = self.ctx.session.truth
            if truth and state.get("F") is not None:
                try:
                    scores = evaluate_fundamental(dict(state), dict(truth))
                except Exception:  # the truth cannot judge these matches
                    scores = {}
                if "inlier_precision" in scores:
                    text += (f"  \nAgainst the ground truth: {scores['inlier_precision']:.1%} of the inliers are right "
                             f"matches, and {scores['inlier_recall']:.1%} of the right matches are inliers.")
            self.summary_md.content = text


INTERACTIONS: list[type[Interaction]] = [EpipolarExplorer, PoseCandidates, MatchColours]

__all__ = ["INTERACTIONS", "EpipolarExplorer", "PoseCandidates", "MatchColours", "TwoViewGeometry", "PixelPick",
           "PointMove", "ImagePlacement", "CandidateAnalysis", "camera_centre", "pixel_ray", "lift_pixels",
           "click_to_pixel", "project_point", "epipolar_plane_corners", "image_placement", "candidate_layout",
           "candidate_points", "check_pixel", "fundamental_from_pose", "two_view_geometry", "scene_depths", "pick",
           "move", "explorer_overlays", "draw_overlays", "match_pair_image", "analyse_candidates"]
