"""Where cameras see things and where the viewer draws them: the camera math interactions share.

Pure functions of a pinhole camera ``x ~ K (R X + t)`` (world to camera ``X_c = R X + t``, OpenCV's
frame: x right, y down, z forward; pixel centres at integers, DESIGN.md 3): a camera's centre, a
pixel's ray, pixels lifted to a depth, a click's ray meeting an image plane drawn at some depth, a
point's projection and depth, the epipolar plane of a point seen by two cameras, and where to draw a
camera's image in its frustum. The epipolar and stereo interactions of the viewer both draw cameras
with their images as clickable planes, so the math lives here, once.

Reference: R. Hartley and A. Zisserman, Multiple View Geometry (2nd ed., 2004), sections 6.2
(back-projection, the camera centre) and 9.1 (the epipolar plane).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lab.core.errors import InvalidValue
from lab.geometry.homogeneous import to_homogeneous


def camera_centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The centre ``C = -R^T t`` ``(3,)`` of a camera with ``X_c = R X + t`` (H&Z section 6.2.4)."""
    R = np.asarray(R, dtype=np.float64)
    return -R.T @ np.asarray(t, dtype=np.float64).reshape(3)


def pixel_ray(K: np.ndarray, R: np.ndarray, t: np.ndarray,
              pixel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Back-projection of a pixel: the ray's origin (the camera centre) and unit direction, ``(3,)`` each, in
    world.

    ``X(s) = C + s d`` with ``C = -R^T t`` and ``d ~ R^T K^-1 (u, v, 1)``: every point on it projects to
    ``(u, v)``; ``s > 0`` is in front of the camera. Reference: H&Z section 6.2.2 (eq. 6.14).
    """
    K = np.asarray(K, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    direction = R.T @ np.linalg.solve(K, to_homogeneous(np.asarray(pixel, dtype=np.float64).reshape(1, 2))[0])
    return camera_centre(R, t), direction / np.linalg.norm(direction)


def lift_pixels(K: np.ndarray, R: np.ndarray, t: np.ndarray, pixels: np.ndarray, depth: float) -> np.ndarray:
    """The world points ``(N, 3)`` at camera depth ``depth`` (``Z_c = depth``) that project to ``pixels``
    ``(N, 2)``.

    ``X = R^T (depth K^-1 (u, v, 1) - t)``: the pixels placed on the image plane drawn at that depth.
    """
    K = np.asarray(K, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    rays = to_homogeneous(np.asarray(pixels, dtype=np.float64).reshape(-1, 2)) @ np.linalg.inv(K).T
    rays = rays / rays[:, 2:]
    return (depth * rays - np.asarray(t, dtype=np.float64).reshape(3)) @ R


def click_to_pixel(ray_origin: np.ndarray, ray_direction: np.ndarray, K: np.ndarray, R: np.ndarray,
                   t: np.ndarray, depth: float) -> np.ndarray:
    """The pixel ``(2,)`` where a click's ray (world) meets a camera's image plane drawn at depth ``depth``.

    In the camera frame the ray is ``o + s d`` (``o = R o_w + t``, ``d = R d_w``); it meets the plane
    ``Z_c = depth`` at ``s = (depth - o_z) / d_z``, and that point projects to ``K (X / Z)``. Raises
    :class:`InvalidValue` when the ray is parallel to the plane or meets it behind the viewer.
    """
    R = np.asarray(R, dtype=np.float64)
    origin = R @ np.asarray(ray_origin, dtype=np.float64).reshape(3) + \
        np.asarray(t, dtype=np.float64).reshape(3)
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


def epipolar_plane_corners(c1: np.ndarray, c2: np.ndarray, point: np.ndarray, *,
                           extend: float = 1.25) -> np.ndarray:
    """A quad ``(4, 3)`` of the epipolar plane of ``point``: ``c1``, ``c2``, then past ``point`` along both
    rays.

    The plane through both camera centres and a point contains both rays to the point, so it meets
    each image plane in that point's epipolar line (H&Z section 9.1, figure 9.1). Corners:
    ``c1``, ``c2``, ``c2 + extend (X - c2)``, ``c1 + extend (X - c1)``. A point on the baseline
    spans no plane: :class:`InvalidValue`.
    """
    c1, c2, X = (np.asarray(v, dtype=np.float64).reshape(3) for v in (c1, c2, point))
    normal = np.cross(c2 - c1, X - c1)
    scale = np.linalg.norm(c2 - c1) * np.linalg.norm(X - c1)
    if scale == 0 or np.linalg.norm(normal) <= 1e-9 * scale:
        raise InvalidValue("point", "lies on the baseline (the line through both camera centres): it spans "
                                    "no epipolar plane and projects onto the epipoles")
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
    """Place a ``width x height`` image on the plane ``Z_c = depth`` of a camera, so each pixel covers its
    ray.

    The image spans pixel edges ``[-0.5, width - 0.5] x [-0.5, height - 0.5]`` (pixel centres are
    integers, DESIGN.md 3); lifted to depth ``depth`` (:func:`lift_pixels`) it is ``depth width / fx``
    by ``depth height / fy``. viser draws a scene image in its node's x-y plane with u along +x and v
    along +y, so the node takes the camera's orientation ``R^T``. Exact for ``K`` without skew.
    """
    K = np.asarray(K, dtype=np.float64)
    corners_px = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5],
                           [-0.5, height - 0.5]])
    corners = lift_pixels(K, R, t, corners_px, depth)
    centre = lift_pixels(K, R, t, np.array([[(width - 1) / 2.0, (height - 1) / 2.0]]), depth)[0]
    return ImagePlacement(centre, np.asarray(R, dtype=np.float64).T, depth * width / K[0, 0],
                          depth * height / K[1, 1], corners)


__all__ = ["ImagePlacement", "camera_centre", "click_to_pixel", "epipolar_plane_corners", "image_placement",
           "lift_pixels", "pixel_ray", "project_point"]
