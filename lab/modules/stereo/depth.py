"""Depth from disparity, ``Z = f B / (d + offset)``, its uncertainty, and the points and cameras of the pair.

Helpers of :func:`lab.modules.stereo.reconstruct_points` (Hartley & Zisserman, 2nd ed., section
11.12; Szeliski 2022, section 12.1).
"""

from __future__ import annotations

import numpy as np

from lab.core import Cameras, Image, PointCloud
from lab.geometry.camera import as_intrinsics
from lab.modules.stereo._checks import check_baseline


def depth_from_disparity(disparity: np.ndarray, K: np.ndarray, baseline: float, *,
                         disparity_offset: float = 0.0,
                         disparity_std: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Depth ``Z = f B / (d + offset)`` and its uncertainty ``u_z = Z^2 u_d / (f B)`` (first-order propagation
    of a disparity uncertainty ``u_d``), ``(H, W)`` each in metres, 0 where there is no disparity or it is not
    positive.

    Reference: Hartley & Zisserman (2nd ed.), section 11.12; Szeliski (2022), section 12.1.
    """
    K = as_intrinsics(K)
    baseline = check_baseline(baseline)
    d = np.asarray(disparity, dtype=np.float64) + float(disparity_offset)
    valid = (np.asarray(disparity) >= 0) & (d > 0)
    fB = K[0, 0] * baseline
    depth = np.where(valid, fB / np.where(valid, d, 1.0), 0.0)
    return depth, np.where(valid, depth * depth * float(disparity_std) / fB, 0.0)


def point_cloud(depth: np.ndarray, left: Image, K: np.ndarray, *, stride: int,
                max_depth: float) -> PointCloud:
    """The pixels with a depth (at most ``max_depth`` unless it is 0), every ``stride``-th along rows and
    columns, back-projected ``X = Z K^-1 (x, y, 1)`` into the rectified left camera frame and coloured by
    the left image."""
    keep = depth > 0
    if max_depth > 0:
        keep &= depth <= max_depth
    grid = np.zeros_like(keep)
    grid[::int(stride), ::int(stride)] = True
    rows, columns = np.nonzero(keep & grid)
    Z = depth[rows, columns]
    y_n = (rows - K[1, 2]) / K[1, 1]
    x_n = (columns - K[0, 2] - K[0, 1] * y_n) / K[0, 0]
    xyz = np.stack([x_n * Z, y_n * Z, Z], axis=1)
    pixels = left.pixels[rows, columns]
    colors = np.repeat(pixels[:, None], 3, axis=1) if pixels.ndim == 1 else pixels
    return PointCloud(xyz, colors.astype(np.float64))


def rectified_cameras(K: np.ndarray, baseline: float, disparity_offset: float, width: int,
                      height: int) -> Cameras:
    """The rectified pair: the left camera at the origin, the right one ``baseline`` metres along x, its
    principal point ``disparity_offset`` px further right."""
    K_right = K.copy()
    K_right[0, 2] += float(disparity_offset)
    B = check_baseline(baseline)
    return Cameras(np.stack([K, K_right]), np.stack([np.eye(3), np.eye(3)]),
                   np.array([[0.0, 0.0, 0.0], [-B, 0, 0]]), width, height)
