"""Synthetic two-view correspondences with exact truth: random 3D points seen by two known cameras.

The default scene of the epipolar module's ``correspondences`` dataset (:mod:`lab.modules.epipolar`, whose
``datasets`` also hold the rendered pair and a user's photos), kept here because other code builds two-view
scenes with it. Conventions (DESIGN.md section 3): camera 1 is the world frame (``R1 = I``, ``t1 = 0``);
camera 2 sees ``X_2 = R X_1 + t``; ``x2^T F x1 = 0``; ``E = [t]_x R`` and ``F = K2^-T E K1^-1``.

:func:`correspondences` gives exact truth, controlled noise and outliers, and degenerate configurations on
demand (all points on one plane or one line, zero baseline). Its images show each point as a coloured dot,
and each point gets a random descriptor shared by its two views, so the matching step finds exactly the
generated matches (outliers included).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np

from lab.core import Image, ImageSet, InvalidValue, Loaded, Points2D, Range
from lab.geometry.camera import project_points
from lab.geometry.rotations import look_at, rotvec_to_matrix, skew
from lab.geometry.two_view import fundamental_from_pose

#: Length of the synthetic descriptors (SIFT's).
DESCRIPTOR_SIZE = 128


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _line_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Distance (px) of each ``x2`` from its epipolar line ``F x1``, ``(N,)`` (to place the outliers)."""
    lines = np.column_stack([x1, np.ones(len(x1))]) @ F.T
    return np.abs(np.sum(lines[:, :2] * x2, axis=1) + lines[:, 2]) / np.linalg.norm(lines[:, :2], axis=1)


def relative_pose(baseline: float, distance: float, rng: np.random.Generator, *,
                  jitter_deg: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Camera 2 at ``baseline`` from camera 1 (mostly sideways), turned towards the point ``(0, 0,
    distance)``.

    The direction of the baseline is random, within 30 degrees of the image plane's x axis (either
    side) and tilted up or down by at most 15 degrees; on top of looking at the scene centre the
    camera is turned by a random rotation of at most ``jitter_deg`` degrees. With ``baseline = 0``
    the two cameras share a centre (a pure rotation). Returns ``R`` (3, 3), ``t`` (3,) with
    ``X_2 = R X_1 + t`` and ``|t| = baseline``.
    """
    azimuth = rng.uniform(-np.pi / 6, np.pi / 6) + (np.pi if rng.random() < 0.5 else 0.0)
    elevation = rng.uniform(-np.pi / 12, np.pi / 12)
    direction = np.array([np.cos(elevation) * np.cos(azimuth), np.sin(elevation),
                          np.cos(elevation) * np.sin(azimuth)])
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
                    distance: Annotated[float, Range(0.5, 1000.0)] = 5.0,
                    depth_range: Annotated[float, Range(0.0, 1000.0)] = 4.0,
                    width: Annotated[int, Range(32, 4096)] = 640,
                    height: Annotated[int, Range(32, 4096)] = 480,
                    fx: Annotated[float, Range(10.0, 1e5)] = 600.0,
                    fy: Annotated[float, Range(10.0, 1e5)] = 600.0,
                    cx: float = 319.5, cy: float = 239.5, seed: int = 0) -> Loaded:
    """Random 3D points seen by two known cameras: exact truth, Gaussian noise and wrong matches.

    Camera 1 is the world frame; camera 2 stands ``baseline`` away (mostly sideways) and looks at the
    scene centre ``(0, 0, distance)`` (:func:`relative_pose`). Points fill the part of camera 1's
    view between depths ``distance -+ depth_range / 2`` and are kept only where both cameras see them
    (a 4 px border). Both observations get independent Gaussian noise of ``noise_px`` per axis; then
    a fraction ``outlier_rate`` of the matches is replaced by a wrong point in image 2, drawn
    uniformly over the image but at least 10 px from its true epipolar line (and from
    the true point), so it is unambiguously an outlier.

    ``structure`` "plane" puts all points on one tilted plane and "line" on one 3D line, and
    ``baseline = 0`` makes a pure rotation: the degenerate inputs for which F is not determined.

    Args:
        num_points: number of matches.
        baseline: distance between the camera centres (the scene is at ``distance``).
        noise_px: standard deviation of the pixel noise per axis on both images.
        outlier_rate: fraction of the matches that are wrong.
        structure: "volume" (a general scene), "plane" or "line" (degenerate).
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
    ``x2`` (M, 2). Truth: ``K1``, ``K2``, ``R``, ``t`` (``|t| = baseline``), ``F`` (unit norm), ``E``
    (``[t/|t|]_x R``), ``points3d`` (M, 3) in camera 1's frame, ``x1_exact``, ``x2_exact`` (the
    noise-free projections), ``outliers`` (M,) bool, ``keypoint_track`` (2M,) the point each
    keypoint observes (-1 for an outlier's wrong point).
    """
    if num_points < 8:
        raise InvalidValue("num_points", f"needs at least 8 matches, got {num_points}")
    if not (0 <= cx < width and 0 <= cy < height):
        raise InvalidValue("cx", f"the principal point ({cx}, {cy}) must lie inside the {width}x{height} "
                                 "image")
    if structure == "volume" and depth_range >= 2 * distance:
        raise InvalidValue("depth_range", f"must be less than twice the distance ({2 * distance:g}) so that "
                                          "every point lies in front of camera 1")
    rng = np.random.default_rng(seed)
    K = intrinsics(fx, fy, cx, cy)
    R, t = relative_pose(baseline, distance, rng)
    half_width = distance * max(cx, width - 1 - cx) / fx
    half_height = distance * max(cy, height - 1 - cy) / fy
    border = 4.0
    points = np.zeros((0, 3))
    for _attempt in range(50):
        candidates = _sample_structure(structure, 4 * num_points, distance, depth_range, half_width,
                                       half_height, rng)
        depth2 = candidates @ R[2] + t[2]
        p1 = project_points(candidates, K, None, np.eye(3), np.zeros(3))
        p2 = project_points(candidates, K, None, R, t)
        inside = (candidates[:, 2] > 1e-3 * distance) & (depth2 > 1e-3 * distance)
        for p in (p1, p2):
            inside &= (p[:, 0] >= border) & (p[:, 0] <= width - 1 - border)
            inside &= (p[:, 1] >= border) & (p[:, 1] <= height - 1 - border)
        points = np.concatenate([points, candidates[inside]])[:num_points]
        if len(points) == num_points:
            break
    else:
        raise InvalidValue("baseline", f"found only {len(points)} of {num_points} points seen by both "
                                       "cameras; lower the baseline or raise the distance")
    exact1 = project_points(points, K, None, np.eye(3), np.zeros(3))
    exact2 = project_points(points, K, None, R, t)
    x1 = exact1 + rng.normal(0.0, noise_px, exact1.shape) if noise_px > 0 else exact1.copy()
    x2 = exact2 + rng.normal(0.0, noise_px, exact2.shape) if noise_px > 0 else exact2.copy()
    F = fundamental_from_pose(K, K, R, t) if baseline > 0 else np.zeros((3, 3))
    outliers = np.zeros(num_points, dtype=bool)
    outliers[rng.choice(num_points, round(outlier_rate * num_points), replace=False)] = True
    wrong = np.flatnonzero(outliers)
    while len(wrong):
        x2[wrong] = rng.uniform([border, border], [width - 1 - border, height - 1 - border], (len(wrong), 2))
        far = (np.linalg.norm(x2[wrong] - exact2[wrong], axis=1) > 10.0)
        if baseline > 0:
            far &= _line_distance(F, exact1[wrong], x2[wrong]) > 10.0
        wrong = wrong[~far]
    colors = _point_colors(num_points, rng)
    base = rng.random((num_points, DESCRIPTOR_SIZE))
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    descriptors = np.concatenate([base, base + rng.normal(0.0, 0.01, base.shape)]).astype(np.float32)
    index = np.arange(num_points)
    keypoints = Points2D(np.concatenate([x1, x2]), view=np.repeat([0, 1], num_points),
                         colors=np.concatenate([colors, colors]), image="images")
    track = np.concatenate([index, np.where(outliers, -1, index)])
    images = ImageSet((_dot_image(x1, colors, width, height, "view 0"),
                       _dot_image(x2, colors, width, height, "view 1")))
    direction = t / baseline if baseline > 0 else np.zeros(3)
    state = {"images": images, "K1": K, "K2": K.copy(), "keypoints": keypoints, "descriptors": descriptors,
             "matches": np.column_stack([index, num_points + index]), "x1": x1, "x2": x2}
    truth = {"K1": K, "K2": K.copy(), "R": R, "t": t, "F": F, "E": skew(direction) @ R, "points3d": points,
             "x1_exact": exact1, "x2_exact": exact2, "outliers": outliers, "keypoint_track": track}
    description = (f"Synthetic correspondences: {num_points} points ({structure}) at {distance:g} +- "
                   f"{depth_range / 2:g}, baseline {baseline:g}, noise {noise_px:g} px, "
                   f"{int(outliers.sum())} outliers ({outlier_rate:.0%}), {width}x{height} px, fx={fx:g}")
    return Loaded(state, truth, description)


def _point_colors(count: int, rng: np.random.Generator) -> np.ndarray:
    """Saturated random colours ``(count, 3)`` in [0, 1] (random hues, through OpenCV's HSV)."""
    import cv2

    hsv = np.stack([rng.uniform(0, 360, count), rng.uniform(0.6, 1.0, count), rng.uniform(0.75, 1.0, count)],
                   axis=-1).astype(np.float32)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0].astype(np.float64)


__all__ = ["DESCRIPTOR_SIZE", "correspondences", "intrinsics", "relative_pose"]
