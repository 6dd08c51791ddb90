"""Lesson 04, structure from motion: fill in the three functions, then run

    vision-lab grade 04-sfm starter.py

You may import numpy, scipy and cv2 (not the lab's own implementation). Keep the signatures.
"""

import numpy as np


def estimate_poses_linear(points3d, observations, K):
    """Linear PnP (DLT): the pose [R | t] of every camera from the known 3D points it sees.

    Args:
        points3d: (N, 3) float64 known world points.
        observations: lab.core.Points2D. ``observations.xy`` (M, 2) float64 pixels,
            ``observations.view`` (M,) int the camera (0 .. V-1), ``observations.ids`` (M,) int the
            3D point: camera v sees ``points3d[ids[k]]`` at ``xy[k]`` for every k with ``view[k] == v``.
        K: (3, 3) float64 intrinsics shared by all cameras.

    Returns:
        (V, 3, 4) float64: ``[R | t]`` of cameras 0 .. V-1 (``X_cam = R X + t``), R a rotation
        (det +1), the points in front of the camera. Work in normalized coordinates K^-1 x, normalize
        both point sets (Hartley), solve the 2n x 12 DLT, undo the normalizations, fix the sign of P,
        project its left 3 x 3 block onto SO(3) and divide its last column by that block's mean
        singular value.
    """
    raise NotImplementedError


def triangulate_points_linear(observations, poses, K):
    """Linear (DLT) triangulation of every point from all the cameras that see it.

    Args:
        observations: lab.core.Points2D as above; point n is seen at ``xy[k]`` by camera ``view[k]``
            for every k with ``ids[k] == n``.
        poses: (V, 3, 4) float64 ``[R | t]`` of the cameras.
        K: (3, 3) float64.

    Returns:
        (N, 3) float64, row n the point with id n (N = observations.ids.max() + 1). With
        P = K [R | t] (rows p1, p2, p3), each view seeing the point at pixel (x, y) gives the rows
        x p3 - p1 and y p3 - p2 of A X = 0; X is the last right singular vector, de-homogenized.
    """
    raise NotImplementedError


def jacobian_sparsity(camera_indices, point_indices, num_cameras, num_points):
    """Which entries of the bundle-adjustment Jacobian can be non-zero.

    Args:
        camera_indices: (M,) int, the camera of each observation.
        point_indices: (M,) int, the 3D point of each observation.
        num_cameras: V. num_points: N.

    Returns:
        (2 M, 6 V + 3 N) bool. Rows 2 i and 2 i + 1 are the u and v residuals of observation i;
        camera c owns columns 6 c .. 6 c + 5 (rotation, translation), point p columns
        6 V + 3 p .. 6 V + 3 p + 2.
    """
    raise NotImplementedError
