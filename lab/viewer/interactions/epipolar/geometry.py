"""The epipolar interactions' math: which two-view geometry is drawn, and what a pixel or a point determines.

Pure functions (no viser), tested directly: the session's F and pose, else the ground truth's
(:func:`two_view_geometry`), the matched pairs to triangulate (:func:`observed_pairs`), how deep the
scene is (:func:`scene_depths`), a picked pixel's epipolar line, ray and plane (:func:`pick`), a 3D
point's projections and lines (:func:`move`), and the 2D overlays of both (:func:`explorer_overlays`).
World coordinates are camera 1's frame: camera 2 sees ``X_2 = R X_1 + t``.

Reference: R. Hartley and A. Zisserman, Multiple View Geometry (2nd ed., 2004), sections 6.2.2
(back-projection of a pixel to a ray) and 9.1 (the epipolar plane and lines).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from lab.core.errors import InvalidValue, MissingInput
from lab.core.values import ImageSet, Points2D, Segments2D
from lab.geometry.camera_views import camera_centre, epipolar_plane_corners, lift_pixels, project_point
from lab.geometry.triangulation import point_depths, projection_matrix, triangulate_dlt
from lab.geometry.two_view import fundamental_from_pose
from lab.modules.epipolar import clip_lines, epipolar_lines, epipoles

#: Colours (RGB, 0-255) of a picked pixel and its line, and of the moved 3D point and its lines.
PICK_COLOR = (255, 210, 0)
POINT_COLOR = (255, 0, 200)
#: The state values the geometry is drawn from (:func:`two_view_geometry`, :func:`observed_pairs`); the
#: interactions read them through ``ctx.values`` (each one of the pipeline's views).
GEOMETRY_READS = ("images", "K1", "K2", "F", "R", "t", "pose", "x1", "x2", "inliers")


def check_pixel(pixel: Any, width: int, height: int, image: int) -> np.ndarray:
    """``pixel`` as a finite ``(2,)`` array inside image ``image`` (pixel edges ``[-0.5, size - 0.5]``)."""
    try:
        uv = np.asarray(pixel, dtype=np.float64).reshape(2)
    except (TypeError, ValueError):
        raise InvalidValue("pixel", f"expected two numbers (u, v), got {pixel!r}") from None
    if not np.all(np.isfinite(uv)):
        raise InvalidValue("pixel", f"(u, v) must be finite numbers, got {tuple(uv)}")
    if not (-0.5 <= uv[0] <= width - 0.5 and -0.5 <= uv[1] <= height - 0.5):
        raise InvalidValue("pixel", f"({uv[0]:g}, {uv[1]:g}) is outside image {image} ({width}x{height}: "
                                    f"u in [-0.5, {width - 0.5:g}], v in [-0.5, {height - 0.5:g}])")
    return uv


# ----------------------------------------------------------------------------------------------------
# Which geometry is shown: the session's, else the ground truth
# ----------------------------------------------------------------------------------------------------
class Pose(NamedTuple):
    """Both cameras' intrinsics and camera 2's pose ``X_2 = R X_1 + t``, all known."""

    K1: np.ndarray
    K2: np.ndarray
    R: np.ndarray
    t: np.ndarray


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
    def pose(self) -> Pose | None:
        """Both K and the pose when all are known, else None."""
        if self.K1 is None or self.K2 is None or self.R is None or self.t is None:
            return None
        return Pose(self.K1, self.K2, self.R, self.t)

    @property
    def has_pose(self) -> bool:
        return self.pose is not None

    def require_pose(self) -> Pose:
        """:attr:`pose`; :class:`MissingInput` (what to run) when it is not known."""
        pose = self.pose
        if pose is None:
            raise MissingInput("pose", "no relative pose yet: run recover_pose (this dataset has no ground "
                                       "truth pose to show instead)")
        return pose

    def camera(self, image: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(K, R, t)`` of camera ``image`` (1: the world frame; 2: at the pose), None when unknown."""
        if image == 1:
            return None if self.K1 is None else (self.K1, np.eye(3), np.zeros(3))
        pose = self.pose
        return None if pose is None else (pose.K2, pose.R, pose.t)

    def require_camera(self, image: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`camera`; :class:`MissingInput` when camera ``image`` is not placed."""
        camera = self.camera(image)
        if camera is None:
            raise MissingInput("K1" if image == 1 else "pose", f"camera {image} is not placed in the scene")
        return camera

    def centres(self) -> np.ndarray:
        """Camera centres ``(2, 3)``: the origin and ``-R^T t``."""
        pose = self.require_pose()
        return np.stack([np.zeros(3), camera_centre(pose.R, pose.t)])


def matrix_or_none(value: Any) -> np.ndarray | None:
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
    K1 = matrix_or_none(state.get("K1"))
    K2 = matrix_or_none(state.get("K2"))
    if K1 is None or K2 is None:
        K1, K2 = matrix_or_none(truth.get("K1")), matrix_or_none(truth.get("K2"))
    R = t = None
    pose_source = ""
    if state.get("R") is not None and state.get("t") is not None:
        R, t, pose_source = np.asarray(state["R"], float), np.asarray(state["t"],
                                                                      float), "the session (refine_pose)"
    elif state.get("pose") is not None:
        pose = np.asarray(state["pose"], dtype=np.float64)
        R, t, pose_source = pose[:, :3], pose[:, 3], "the session (recover_pose)"
    elif truth.get("R") is not None and truth.get("t") is not None and np.linalg.norm(truth["t"]) > 0:
        R, t, pose_source = np.asarray(truth["R"], float), np.asarray(truth["t"], float), "the ground truth"
    F = matrix_or_none(state.get("F"))
    f_source = "the session (the last F written: RANSAC's, else the 8-point's)" if F is not None else ""
    if F is None and matrix_or_none(truth.get("F")) is not None:
        F, f_source = np.asarray(truth["F"], dtype=np.float64), "the ground truth"
    if F is None and R is not None and t is not None and K1 is not None and K2 is not None:
        F, f_source = fundamental_from_pose(K1, K2, R, t), f"the pose from {pose_source}"
    return TwoViewGeometry(sizes, K1, K2, F, R, t, f_source, pose_source)


def observed_pairs(state: Mapping[str, Any], truth: Mapping[str, Any]) -> tuple[np.ndarray,
                                                                                np.ndarray] | None:
    """Matched pixels to triangulate: the session's inliers (or matches), else the truth's exact pairs."""
    x1, x2 = state.get("x1"), state.get("x2")
    if x1 is not None and x2 is not None and len(x1) > 0 and len(x1) == len(x2):
        x1, x2 = np.asarray(x1, dtype=np.float64), np.asarray(x2, dtype=np.float64)
        inliers = state.get("inliers")
        if inliers is not None and np.shape(inliers) == (len(x1),) and np.any(inliers):
            x1, x2 = x1[np.asarray(inliers, bool)], x2[np.asarray(inliers, bool)]
        return x1, x2
    if truth.get("x1_exact") is not None and len(truth["x1_exact"]) > 0:
        return np.asarray(truth["x1_exact"], dtype=np.float64), np.asarray(truth["x2_exact"],
                                                                           dtype=np.float64)
    return None


def scene_depths(geometry: TwoViewGeometry, pairs: tuple[np.ndarray, np.ndarray] | None) -> tuple[float,
                                                                                                  float]:
    """A typical and a far depth in camera 1 (the median and 95th percentile of the triangulated pairs).

    Sizes the drawing: the image planes, the rays' length. In the pose's units (the session's
    baseline is 1); without a pose or pairs, 5 and 8 baselines.
    """
    baseline = float(np.linalg.norm(geometry.t)) if geometry.t is not None else 1.0
    baseline = baseline if baseline > 0 else 1.0
    pose = geometry.pose
    if pose is not None and pairs is not None and len(pairs[0]):
        step = max(1, len(pairs[0]) // 500)
        x1, x2 = pairs[0][::step], pairs[1][::step]
        P = np.stack([projection_matrix(pose.K1, np.eye(3), np.zeros(3)),
                      projection_matrix(pose.K2, pose.R, pose.t)])
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
    """A 3D point (camera 1 frame) and its images: ``pixels`` ``(2, 2)`` and ``depths`` ``(2,)`` in image 1
    and image 2, ``lines`` ``(2, 3)`` its epipolar lines in image 1 (``F^T x2``) and image 2 (``F x1``), with
    ``F`` the pose's, ``segments`` those lines clipped to each image, ``plane`` ``(4, 3)`` the epipolar
    quad."""

    point: np.ndarray
    pixels: np.ndarray
    depths: np.ndarray
    lines: np.ndarray
    segments: tuple[np.ndarray | None, np.ndarray | None]
    plane: np.ndarray


def _clipped(line: np.ndarray, width: int, height: int) -> np.ndarray | None:
    start, end, valid = clip_lines(line.reshape(1, 3), width, height)
    return np.stack([start[0], end[0]]) if valid[0] else None


def pick(geometry: TwoViewGeometry, pixel: Any, *, image: int = 1, far: float = 10.0) -> PixelPick:
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
    line = epipolar_lines(geometry.F, uv.reshape(1, 2), image=1 if image == 1 else 2)[0]
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
    pose = geometry.require_pose()
    try:
        X = np.asarray(point, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise InvalidValue("point", f"expected three numbers (x, y, z), got {point!r}") from None
    if not np.all(np.isfinite(X)):
        raise InvalidValue("point", f"(x, y, z) must be finite numbers, got {tuple(X)}")
    pixels, depths = [], []
    for K, R, t in ((pose.K1, np.eye(3), np.zeros(3)), (pose.K2, pose.R, pose.t)):
        pixel, depth = project_point(K, R, t, X)
        pixels.append(pixel)
        depths.append(depth)
    c1, c2 = geometry.centres()
    plane = epipolar_plane_corners(c1, c2, X, extend=extend)
    F = fundamental_from_pose(pose.K1, pose.K2, pose.R, pose.t)
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
        overlays[picked.image - 1].append(Points2D(picked.pixel.reshape(1, 2),
                                                   colors=_unit_color(PICK_COLOR)))
        if picked.segment is not None:
            overlays[2 - picked.image].append(Segments2D(picked.segment[:1], picked.segment[1:],
                                                         colors=_unit_color(PICK_COLOR)))
    if moved is not None:
        for index in (0, 1):
            if moved.depths[index] > 0:
                overlays[index].append(Points2D(moved.pixels[index].reshape(1, 2),
                                                colors=_unit_color(POINT_COLOR)))
            segment = moved.segments[index]
            if segment is not None:
                overlays[index].append(Segments2D(segment[:1], segment[1:], colors=_unit_color(POINT_COLOR)))
    return overlays


def label_anchors(centres: np.ndarray, planes: list[np.ndarray], *, spread: float) -> np.ndarray:
    """Where the explorer writes "camera 1" and "camera 2": ``(n, 3)``, one per camera centre ``centres[i]``
    with its image plane's corners ``planes[i]`` (``(4, 3)``: top-left, top-right, bottom-right, bottom-left,
    :func:`lab.geometry.camera_views.image_placement`).

    One camera: its centre. Two: above the outer top corner of each plane (camera 1's on the side away from
    camera 2, and back), pushed apart along the baseline by ``spread`` and lifted by a fifth of it. Seen from
    behind the cameras, as the tab's first camera looks, the centres of a short baseline are a few pixels
    apart on screen and labels there overlap; these are at least ``2 spread`` apart along the baseline.
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if len(centres) != 2:
        return centres.copy()
    corners = [np.asarray(c, dtype=np.float64).reshape(4, 3) for c in planes]
    baseline = centres[1] - centres[0]
    if np.linalg.norm(baseline) < 1e-12:  # one centre: apart along camera 1's image rows instead
        baseline = corners[0][1] - corners[0][0]
    along = baseline / max(float(np.linalg.norm(baseline)), 1e-300)
    anchors = []
    for side, plane in zip((-1.0, 1.0), corners, strict=True):
        top = plane[:2]  # its top-left and top-right corners
        outer = top[int(np.argmax(side * (top @ along)))]
        lift = plane[0] - plane[3]  # bottom-left to top-left: up in the picture
        lift = lift / max(float(np.linalg.norm(lift)), 1e-300)
        anchors.append(outer + side * spread * along + 0.2 * spread * lift)
    return np.stack(anchors)


__all__ = ["GEOMETRY_READS", "PICK_COLOR", "POINT_COLOR", "PixelPick", "PointMove", "TwoViewGeometry",
           "check_pixel", "explorer_overlays", "label_anchors", "matrix_or_none", "move", "observed_pairs",
           "pick", "scene_depths", "two_view_geometry"]
