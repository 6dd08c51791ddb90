"""Synthetic two-view correspondences with exact truth: random 3D points seen by two known cameras.

The default scene of the epipolar module's ``correspondences`` dataset (:mod:`lab.modules.epipolar`, whose
``datasets`` also hold the rendered pair and a user's photos), kept here because other code builds two-view
scenes with it. Conventions (DESIGN.md section 3): camera 1 is the world frame (``R1 = I``, ``t1 = 0``);
camera 2 sees ``X_2 = R X_1 + t``; ``x2^T F x1 = 0``; ``E = [t]_x R`` and ``F = K2^-T E K1^-1``.

:func:`correspondences` gives exact truth, controlled noise and outliers, and degenerate configurations on
demand (all points on one plane or one line, zero baseline), and wrong matches built to exercise a
cheirality test (:func:`pose_candidates`): wrong matches that RANSAC rejects but that vote for the pose with
``t`` reversed (``outlier_placement``), and wrong matches on their epipolar lines, which RANSAC keeps, that
lie behind both cameras (``behind_rate``). Its images show each point as a coloured dot, and each point gets a
random descriptor shared by its two views, so the matching step finds exactly the generated matches (outliers
included).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np

from lab.core import Image, ImageSet, InvalidValue, Loaded, Points2D, Range
from lab.geometry.camera import project_points
from lab.geometry.rotations import look_at, rotvec_to_matrix, skew
from lab.geometry.triangulation import point_depths, triangulate_dlt
from lab.geometry.two_view import fundamental_from_pose

#: Length of the synthetic descriptors (SIFT's).
DESCRIPTOR_SIZE = 128

#: Where :func:`correspondences` puts its wrong matches (``outlier_placement``).
OutlierPlacement = Literal["uniform", "reversed_pose"]

#: How far (px) a ``"reversed_pose"`` wrong match is moved off its epipolar line: far enough that no other F
#: explains some of them together with the right matches (at 10 to 40 px, RANSAC kept a few with a compromise
#: F).
OFF_LINE_PX = (30.0, 80.0)


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _line_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Distance (px) of each ``x2`` from its epipolar line ``F x1``, ``(N,)`` (to place the outliers)."""
    lines = np.column_stack([x1, np.ones(len(x1))]) @ F.T
    return np.abs(np.sum(lines[:, :2] * x2, axis=1) + lines[:, 2]) / np.linalg.norm(lines[:, :2], axis=1)


def relative_pose(baseline: float, distance: float, rng: np.random.Generator, *,
                  jitter_deg: float = 3.0, forward: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Camera 2 at ``baseline`` from camera 1 (mostly sideways), turned towards the point ``(0, 0,
    distance)``.

    The direction of the baseline is random, within 30 degrees of the image plane's x axis (either
    side) and tilted up or down by at most 15 degrees; on top of looking at the scene centre the
    camera is turned by a random rotation of at most ``jitter_deg`` degrees. ``forward`` moves camera 2
    towards the scene instead, within 3 degrees of camera 1's optical axis (the epipoles near the image
    centres; swapping the two images then reverses the motion, which a cheirality test sees). With
    ``baseline = 0`` the two cameras share a centre (a pure rotation). Returns ``R`` (3, 3), ``t`` (3,)
    with ``X_2 = R X_1 + t`` and ``|t| = baseline``.
    """
    azimuth = rng.uniform(-np.pi / 6, np.pi / 6) + (np.pi if rng.random() < 0.5 else 0.0)
    elevation = rng.uniform(-np.pi / 12, np.pi / 12)
    direction = np.array([np.cos(elevation) * np.cos(azimuth), np.sin(elevation),
                          np.cos(elevation) * np.sin(azimuth)])
    if forward:  # the same draws, the direction within 3 degrees of the optical axis
        tilt = np.radians(3.0) * abs(elevation) / (np.pi / 12)
        direction = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])
    centre = baseline * direction
    target = np.array([0.0, 0.0, distance])
    R_look, _ = look_at(centre, target)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R = rotvec_to_matrix(np.radians(rng.uniform(0.5, 1.0) * jitter_deg) * axis) @ R_look
    t = -R @ centre
    return R, t


def _sample_structure(structure: str, count: int, distance: float, depth_range: float, half_width: float,
                      half_height: float, rng: np.random.Generator) -> np.ndarray:
    """``count`` candidate 3D points (camera-1 frame) of the requested structure, ``(count, 3)``."""
    if structure == "volume":
        z = rng.uniform(distance - depth_range / 2, distance + depth_range / 2, count)
        x = rng.uniform(-1, 1, count) * half_width * z / distance
        y = rng.uniform(-1, 1, count) * half_height * z / distance
        return np.column_stack([x, y, z])
    centre = np.array([0.0, 0.0, distance])
    if structure == "plane":  # a plane through the scene centre, tilted 20-40 degrees from fronto-parallel
        tilt = np.radians(rng.uniform(20, 40))
        phi = rng.uniform(0, 2 * np.pi)
        normal = np.array([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), -np.cos(tilt)])
        u = np.cross(normal, [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        a, b = rng.uniform(-1.5, 1.5, (2, count))
        return centre + a[:, None] * u * half_width + b[:, None] * v * half_width
    # "line": a 3D line through the scene centre, oblique to the image plane
    direction = np.array([1.0, rng.uniform(-0.5, 0.5), rng.uniform(0.3, 0.8)])
    direction /= np.linalg.norm(direction)
    s = rng.uniform(-1.5, 1.5, count) * half_width
    return centre + s[:, None] * direction


def pose_candidates(R: np.ndarray, t: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The four relative poses the essential matrix of ``(R, t)`` admits, named by what they are.

    ``"true"`` ``(R, t)``, ``"reversed"`` ``(R, -t)``, ``"twisted"`` ``(R_pi R, t)`` and
    ``"twisted_reversed"`` ``(R_pi R, -t)``, with ``R_pi = 2 u u^T - I`` the half turn about the baseline
    ``u = t / |t|``: all four have ``[t]_x R`` as their essential matrix, up to sign (H&Z result 9.19 and
    figure 9.12).
    """
    u = t / np.linalg.norm(t)
    twisted = (2.0 * np.outer(u, u) - np.eye(3)) @ R
    return {"true": (R, t), "reversed": (R, -t), "twisted": (twisted, t), "twisted_reversed": (twisted, -t)}


def triangulated_depths(x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray, R: np.ndarray,
                        t: np.ndarray) -> np.ndarray:
    """The depths ``(2, N)`` in camera 1 and camera 2 of the matches triangulated with the pose ``(R, t)``:
    the linear DLT on normalized coordinates ``K^-1 x`` with ``P1 = [I | 0]``, ``P2 = [R | t]``, as a
    cheirality test does (NaN for a point at infinity)."""
    from lab.geometry.camera import pixels_to_normalized

    P = np.stack([np.hstack([np.eye(3), np.zeros((3, 1))]), np.column_stack([R, t])])
    X = triangulate_dlt(P, np.stack([pixels_to_normalized(x1, K1), pixels_to_normalized(x2, K2)]))
    finite = np.all(np.isfinite(X), axis=1)
    depths = point_depths(P, np.where(finite[:, None], X, 0.0))
    return np.where(finite[None], depths, np.nan)


@dataclass(frozen=True)
class _Scene:
    """What :func:`correspondences` draws wrong matches from: the cameras, the volume and the image bounds."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    distance: float
    depth_range: float
    half_width: float
    half_height: float
    width: int
    height: int
    border: float

    def inside(self, xy: np.ndarray) -> np.ndarray:
        return ((xy[:, 0] >= self.border) & (xy[:, 0] <= self.width - 1 - self.border)
                & (xy[:, 1] >= self.border) & (xy[:, 1] <= self.height - 1 - self.border))

    def depths(self, x1: np.ndarray, x2: np.ndarray, pose: str) -> np.ndarray:
        """:func:`triangulated_depths` with candidate ``pose`` of :func:`pose_candidates`, in units of
        ``distance``."""
        R, t = pose_candidates(self.R, self.t)[pose]
        return triangulated_depths(x1, x2, self.K, self.K, R, t) / self.distance

    def mirrored_pairs(self, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Exact pixel pairs ``(K, 2)``, ``K <= count``, of 3D points behind both cameras: of ``-Y`` for
        points ``Y`` of the scene's volume in front of both cameras of the reversed pose ``(R, -t)``, seen
        in both images. They satisfy ``x2^T F x1 = 0``; triangulated with ``(R, t)`` they lie behind both
        cameras."""
        Y = _sample_structure("volume", count, self.distance, self.depth_range, self.half_width,
                              self.half_height, rng)
        in_front = Y @ self.R[2] - self.t[2] > 1e-3 * self.distance
        x1 = project_points(Y, self.K, None, np.eye(3), np.zeros(3))
        x2 = project_points(Y, self.K, None, self.R, -self.t)
        keep = in_front & self.inside(x1) & self.inside(x2)
        return x1[keep], x2[keep]


#: Depths (in units of the scene's distance) a built wrong match keeps from 0 and from infinity under the
#: poses it is built for, so that the estimated pose (not the true one) sorts it the same way.
_NEAR, _FAR = 0.1, 20.0


def _decided(depths: np.ndarray, signs: tuple[int, int]) -> np.ndarray:
    """Which columns of ``depths`` ``(2, N)`` have the ``signs`` (+1 / -1 per camera), clear of 0 and of
    infinity."""
    wanted = np.array(signs, dtype=np.float64)[:, None] * depths
    return np.all((wanted > _NEAR) & (wanted < _FAR), axis=0)


def _built(count: int, draw: Any, what: str) -> tuple[np.ndarray, np.ndarray]:
    """``count`` pairs from ``draw()`` (which returns the pairs of one batch that qualify), batch after
    batch."""
    x1, x2 = np.zeros((0, 2)), np.zeros((0, 2))
    for _attempt in range(50):
        a, b = draw()
        x1, x2 = np.concatenate([x1, a])[:count], np.concatenate([x2, b])[:count]
        if len(x1) == count:
            return x1, x2
    raise InvalidValue("outlier_placement", f"found only {len(x1)} of {count} {what}; lower the rate")


def behind_matches(scene: _Scene, count: int, noise_px: float, right: tuple[np.ndarray, np.ndarray],
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` wrong matches ``(count, 2)`` on their epipolar lines (with the right matches' pixel noise, so
    RANSAC keeps them) that lie behind both cameras of the true pose, and, with the half-turned pose that puts
    the most of the ``right`` matches (exact pixels ``x1``, ``x2``) in front of camera 1, in front of camera 1
    and behind camera 2.

    A cheirality test that counts the points in front of both cameras picks the true pose as long as the
    right matches outnumber these (the reversed pose gets these); one that looks at camera 1 only gives that
    half-turned pose the right matches on its side plus all of these, and one that looks at camera 2 only
    gives the other half-turned pose the rest of the right matches plus all of these: with more of these than
    half the right matches, both pick a wrong pose.
    """
    front = {pose: int(np.sum(scene.depths(*right, pose)[0] > 0)) for pose in ("twisted", "twisted_reversed")}
    twisted = max(front, key=lambda pose: front[pose])

    def draw() -> tuple[np.ndarray, np.ndarray]:
        a, b = scene.mirrored_pairs(4 * count, rng)
        if noise_px > 0:
            a, b = a + rng.normal(0.0, noise_px, a.shape), b + rng.normal(0.0, noise_px, b.shape)
        keep = _decided(scene.depths(a, b, "true"), (-1, -1)) & _decided(scene.depths(a, b, twisted), (1, -1))
        return a[keep], b[keep]

    return _built(count, draw, "wrong matches behind both cameras")


def reversed_pose_outliers(scene: _Scene, count: int,
                           rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` wrong matches ``(count, 2)`` that RANSAC rejects but that vote for the reversed pose: each is
    the image pair of a point behind both cameras (:meth:`_Scene.mirrored_pairs`) with ``x2`` moved off its
    epipolar line by 30 to 80 px (:data:`OFF_LINE_PX`), and triangulated with ``(R, -t)`` it still lies in
    front of both cameras. A cheirality test that counts every match, not only RANSAC's inliers, gives the
    reversed pose all of these: with more of them than right matches, it picks ``(R, -t)``."""
    F = fundamental_from_pose(scene.K, scene.K, scene.R, scene.t)

    def draw() -> tuple[np.ndarray, np.ndarray]:
        a, b = scene.mirrored_pairs(4 * count, rng)
        lines = np.column_stack([a, np.ones(len(a))]) @ F.T
        normals = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
        offsets = rng.uniform(*OFF_LINE_PX, len(a)) * rng.choice([-1.0, 1.0], len(a))
        b = b + offsets[:, None] * normals
        keep = scene.inside(b) & _decided(scene.depths(a, b, "reversed"), (1, 1))
        keep &= _line_distance(F, a, b) >= OFF_LINE_PX[0] - 1e-6
        return a[keep], b[keep]

    return _built(count, draw, "wrong matches that vote for the reversed pose")


def essential_with_opposite_dets(E: np.ndarray) -> np.ndarray:
    """Of ``E`` and ``-E`` (the same essential matrix), the one for which ``np.linalg.svd`` returns ``U`` and
    ``V^T`` whose determinants have opposite signs: a decomposition that does not turn both into rotations
    then builds reflections (det R = -1) instead of rotations (LAPACK flips one factor with the sign of E)."""
    for candidate in (E, -E):
        U, _, Vt = np.linalg.svd(candidate)
        if np.linalg.det(U) * np.linalg.det(Vt) < 0:
            return candidate.copy()
    raise InvalidValue("given_essential", "NumPy's SVD returns factors of equal determinant signs for both "
                                          "E and -E here")


def _dot_image(xy: np.ndarray, colors: np.ndarray, width: int, height: int, name: str) -> Image:
    """A grey image with a filled disc of radius 3 px at each point, in the point's colour."""
    import cv2

    canvas = np.full((height, width, 3), 0.35, dtype=np.float32)
    for (x, y), color in zip(np.round(xy * 4).astype(int), colors.astype(np.float32), strict=True):
        cv2.circle(canvas, (int(x), int(y)), 12, tuple(float(c) for c in color), thickness=-1,
                   lineType=cv2.LINE_AA, shift=2)
    return Image(canvas, name=name)


def correspondences(*, num_points: Annotated[int, Range(8, 20000)] = 400,
                    baseline: Annotated[float, Range(0.0, 20.0)] = 1.0,
                    noise_px: Annotated[float, Range(0.0, 20.0)] = 0.5,
                    outlier_rate: Annotated[float, Range(0.0, 0.9)] = 0.3,
                    structure: Literal["volume", "plane", "line"] = "volume",
                    outlier_placement: OutlierPlacement = "uniform",
                    behind_rate: Annotated[float, Range(0.0, 0.9)] = 0.0,
                    given_essential: Literal["none", "svd_dets_opposite"] = "none",
                    motion: Literal["sideways", "forward"] = "sideways",
                    distance: Annotated[float, Range(0.5, 1000.0)] = 5.0,
                    depth_range: Annotated[float, Range(0.0, 1000.0)] = 4.0,
                    width: Annotated[int, Range(32, 4096)] = 640,
                    height: Annotated[int, Range(32, 4096)] = 480,
                    fx: Annotated[float, Range(10.0, 1e5)] = 600.0,
                    fy: Annotated[float, Range(10.0, 1e5)] = 600.0,
                    cx: float = 319.5, cy: float = 239.5, seed: int = 0) -> Loaded:
    """Random 3D points seen by two known cameras: exact truth, Gaussian noise and wrong matches.

    Camera 1 is the world frame; camera 2 stands ``baseline`` away (mostly sideways, or with
    ``motion = "forward"`` towards the scene) and looks at the scene centre ``(0, 0, distance)``
    (:func:`relative_pose`). Points fill the part of camera 1's view between depths
    ``distance -+ depth_range / 2`` and are kept only where both cameras see them (a 4 px border). Both
    observations get independent Gaussian noise of ``noise_px`` per axis; then a fraction
    ``outlier_rate`` of the matches is replaced by a wrong point in image 2, drawn uniformly over the
    image but at least 10 px from its true epipolar line (and from the true point), so it is
    unambiguously an outlier.

    ``structure`` "plane" puts all points on one tilted plane and "line" on one 3D line, and
    ``baseline = 0`` makes a pure rotation: the degenerate inputs for which F is not determined.

    Two options build wrong matches that decide a cheirality test (both pixels of a match replaced, from a
    random stream of their own: the other options' data stay the same): ``outlier_placement =
    "reversed_pose"`` (:func:`reversed_pose_outliers`: RANSAC rejects them, a test that counts them too votes
    for ``(R, -t)``) and ``behind_rate`` (:func:`behind_matches`: on their epipolar lines, so RANSAC keeps
    them, behind both cameras: a test of one camera's depths picks a half-turned pose).

    Args:
        num_points: number of matches.
        baseline: distance between the camera centres (the scene is at ``distance``).
        noise_px: standard deviation of the pixel noise per axis on both images.
        outlier_rate: fraction of the matches that are wrong.
        structure: "volume" (a general scene), "plane" or "line" (degenerate).
        outlier_placement: "uniform" (wrong matches anywhere at least 10 px off their epipolar lines) or
            "reversed_pose" (off their lines where they vote for the pose with t reversed).
        behind_rate: fraction of the matches replaced by wrong matches on their epipolar lines that lie
            behind both cameras (at most 0.9 together with outlier_rate).
        motion: "sideways" (camera 2 beside camera 1) or "forward" (camera 2 moved towards the scene).
        given_essential: "none", or "svd_dets_opposite": the state holds the true ``E`` (so the pipeline may
            start at its decomposition), of the sign for which ``np.linalg.svd(E)`` returns ``U`` and ``V^T``
            with determinants of opposite signs (:func:`essential_with_opposite_dets`).
        distance: depth of the scene centre in camera 1.
        depth_range: depth extent of the points (volume).
        width: image width in pixels.
        height: image height in pixels.
        fx: focal length along x in pixels (both cameras).
        fy: focal length along y in pixels.
        cx: principal point x in pixels.
        cy: principal point y in pixels.
        seed: random seed of the scene, the noise and the outliers.

    State: ``images`` (dots), ``K1``, ``K2``, ``keypoints`` (Points2D, view 0 then view 1),
    ``descriptors`` (2M, 128), ``matches`` (M, 2) (keypoint ``i`` of view 0 with ``M + i``), ``x1``,
    ``x2`` (M, 2), and ``E`` with ``given_essential``. Truth: ``K1``, ``K2``, ``R``, ``t``
    (``|t| = baseline``), ``F`` (unit norm), ``E`` (``[t/|t|]_x R``), ``points3d`` (M, 3) in camera 1's
    frame, ``x1_exact``, ``x2_exact`` (the noise-free projections of the real points), ``outliers``
    (M,) bool (every wrong match, those of ``behind_rate`` too), ``keypoint_track`` (2M,) the point each
    keypoint observes (-1 for a wrong point).
    """
    built = outlier_placement != "uniform" or behind_rate > 0
    _check_options(num_points, width, height, cx, cy, structure, distance, depth_range, baseline, built,
                   outlier_rate, behind_rate)
    rng = np.random.default_rng(seed)
    K = intrinsics(fx, fy, cx, cy)
    R, t = relative_pose(baseline, distance, rng, forward=motion == "forward")
    half_width = distance * max(cx, width - 1 - cx) / fx
    half_height = distance * max(cy, height - 1 - cy) / fy
    scene = _Scene(K, R, t, distance, depth_range, half_width, half_height, width, height, border=4.0)
    points = _visible_points(scene, structure, num_points, rng)
    exact1 = project_points(points, K, None, np.eye(3), np.zeros(3))
    exact2 = project_points(points, K, None, R, t)
    x1 = exact1 + rng.normal(0.0, noise_px, exact1.shape) if noise_px > 0 else exact1.copy()
    x2 = exact2 + rng.normal(0.0, noise_px, exact2.shape) if noise_px > 0 else exact2.copy()
    F = fundamental_from_pose(K, K, R, t) if baseline > 0 else np.zeros((3, 3))
    outliers = np.zeros(num_points, dtype=bool)
    outliers[rng.choice(num_points, round(outlier_rate * num_points), replace=False)] = True
    _place_uniform_outliers(scene, x2, exact1, exact2, np.flatnonzero(outliers), F if baseline > 0 else None,
                            rng)
    replaced = np.zeros(num_points, dtype=bool)  # both pixels of the match replaced by a built wrong match
    if built:
        replaced = _build_wrong_matches(scene, x1, x2, exact1, exact2, outliers, outlier_placement,
                                        round(behind_rate * num_points), noise_px,
                                        np.random.default_rng([seed, 2]))
    colors = _point_colors(num_points, rng)
    base = rng.random((num_points, DESCRIPTOR_SIZE))
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    descriptors = np.concatenate([base, base + rng.normal(0.0, 0.01, base.shape)]).astype(np.float32)
    index = np.arange(num_points)
    keypoints = Points2D(np.concatenate([x1, x2]), view=np.repeat([0, 1], num_points),
                         colors=np.concatenate([colors, colors]), image="images")
    track = np.concatenate([np.where(replaced, -1, index), np.where(outliers, -1, index)])
    images = ImageSet((_dot_image(x1, colors, width, height, "view 0"),
                       _dot_image(x2, colors, width, height, "view 1")))
    direction = t / baseline if baseline > 0 else np.zeros(3)
    state = {"images": images, "K1": K, "K2": K.copy(), "keypoints": keypoints, "descriptors": descriptors,
             "matches": np.column_stack([index, num_points + index]), "x1": x1, "x2": x2}
    if given_essential != "none":
        if baseline <= 0:
            raise InvalidValue("given_essential", "a pure rotation (baseline 0) has no essential matrix")
        state["E"] = essential_with_opposite_dets(skew(direction) @ R)
    truth = {"K1": K, "K2": K.copy(), "R": R, "t": t, "F": F, "E": skew(direction) @ R, "points3d": points,
             "x1_exact": exact1, "x2_exact": exact2, "outliers": outliers, "keypoint_track": track}
    placed = (" placed to vote for the reversed pose" if outlier_placement == "reversed_pose" else "") + (
        f", {behind_rate:.0%} on their epipolar lines behind both cameras" if behind_rate else "")
    description = (f"Synthetic correspondences: {num_points} points ({structure}) at {distance:g} +- "
                   f"{depth_range / 2:g}, baseline {baseline:g} ({motion}), noise {noise_px:g} px, "
                   f"{int(outliers.sum())} wrong matches ({outlier_rate:.0%}{placed}), {width}x{height} px, "
                   f"fx={fx:g}")
    return Loaded(state, truth, description)


def _check_options(num_points: int, width: int, height: int, cx: float, cy: float, structure: str,
                   distance: float, depth_range: float, baseline: float, built: bool, outlier_rate: float,
                   behind_rate: float) -> None:
    """The option combinations :func:`correspondences` refuses, each named."""
    if num_points < 8:
        raise InvalidValue("num_points", f"needs at least 8 matches, got {num_points}")
    if not (0 <= cx < width and 0 <= cy < height):
        raise InvalidValue("cx", f"the principal point ({cx}, {cy}) must lie inside the {width}x{height} "
                                 "image")
    if structure == "volume" and depth_range >= 2 * distance:
        raise InvalidValue("depth_range", f"must be less than twice the distance ({2 * distance:g}) so that "
                                          "every point lies in front of camera 1")
    if built and (baseline <= 0 or structure != "volume"):
        raise InvalidValue("behind_rate" if behind_rate > 0 else "outlier_placement",
                           "wrong matches built for the cheirality test need a baseline and a volume scene")
    if outlier_rate + behind_rate > 0.9:
        raise InvalidValue("behind_rate", f"outlier_rate + behind_rate must be at most 0.9, got "
                                          f"{outlier_rate + behind_rate:g}")


def _visible_points(scene: _Scene, structure: str, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points ``(count, 3)`` of ``structure`` in front of both cameras and seen in both images."""
    points = np.zeros((0, 3))
    for _attempt in range(50):
        candidates = _sample_structure(structure, 4 * count, scene.distance, scene.depth_range,
                                       scene.half_width, scene.half_height, rng)
        depth2 = candidates @ scene.R[2] + scene.t[2]
        p1 = project_points(candidates, scene.K, None, np.eye(3), np.zeros(3))
        p2 = project_points(candidates, scene.K, None, scene.R, scene.t)
        inside = (candidates[:, 2] > 1e-3 * scene.distance) & (depth2 > 1e-3 * scene.distance)
        inside &= scene.inside(p1) & scene.inside(p2)
        points = np.concatenate([points, candidates[inside]])[:count]
        if len(points) == count:
            return points
    raise InvalidValue("baseline", f"found only {len(points)} of {count} points seen by both cameras; lower "
                                   "the baseline or raise the distance")


def _place_uniform_outliers(scene: _Scene, x2: np.ndarray, exact1: np.ndarray, exact2: np.ndarray,
                            wrong: np.ndarray, F: np.ndarray | None, rng: np.random.Generator) -> None:
    """Replace ``x2`` of the matches ``wrong`` (in place) by points drawn uniformly over image 2, at least
    10 px from the true point and (given ``F``) from its epipolar line."""
    border = scene.border
    while len(wrong):
        x2[wrong] = rng.uniform([border, border], [scene.width - 1 - border, scene.height - 1 - border],
                                (len(wrong), 2))
        far = (np.linalg.norm(x2[wrong] - exact2[wrong], axis=1) > 10.0)
        if F is not None:
            far &= _line_distance(F, exact1[wrong], x2[wrong]) > 10.0
        wrong = wrong[~far]


def _build_wrong_matches(scene: _Scene, x1: np.ndarray, x2: np.ndarray, exact1: np.ndarray,
                         exact2: np.ndarray, outliers: np.ndarray, placement: str, behind: int,
                         noise_px: float, rng: np.random.Generator) -> np.ndarray:
    """Put the wrong matches built for the cheirality test into ``x1``, ``x2`` (in place): the outliers
    placed to vote for the reversed pose, and ``behind`` right matches replaced by wrong ones behind both
    cameras (marked in ``outliers``). Returns which matches were replaced, ``(M,)`` bool."""
    replaced = np.zeros(len(x1), dtype=bool)
    if placement == "reversed_pose" and outliers.any():
        x1[outliers], x2[outliers] = reversed_pose_outliers(scene, int(outliers.sum()), rng)
        replaced |= outliers
    if behind:
        right = np.flatnonzero(~outliers)
        chosen = rng.choice(right, behind, replace=False)
        kept = np.setdiff1d(right, chosen)
        x1[chosen], x2[chosen] = behind_matches(scene, behind, noise_px, (exact1[kept], exact2[kept]), rng)
        outliers[chosen] = True
        replaced[chosen] = True
    return replaced


def _point_colors(count: int, rng: np.random.Generator) -> np.ndarray:
    """Saturated random colours ``(count, 3)`` in [0, 1] (random hues, through OpenCV's HSV)."""
    import cv2

    hsv = np.stack([rng.uniform(0, 360, count), rng.uniform(0.6, 1.0, count), rng.uniform(0.75, 1.0, count)],
                   axis=-1).astype(np.float32)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0].astype(np.float64)


__all__ = ["DESCRIPTOR_SIZE", "OFF_LINE_PX", "OutlierPlacement", "behind_matches", "correspondences",
           "essential_with_opposite_dets", "intrinsics", "pose_candidates", "relative_pose",
           "reversed_pose_outliers", "triangulated_depths"]
