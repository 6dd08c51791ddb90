"""Math shared by several modules: homogeneous coordinates, rotations, the camera model.

Everything here is batched over leading dimensions, float64, and follows the conventions of
DESIGN.md section 3 (OpenCV camera frame, ``X_c = R X_w + t``, distortion (k1, k2, p1, p2, k3)).
"""

from lab.geometry.camera import (DISTORTION_NAMES, as_distortion, as_intrinsics, distort, distort_components,
                                 distort_with_jacobians, normalized_to_pixels, optimal_new_camera_matrix,
                                 pixels_to_normalized, project, project_points, transform_points, undistort,
                                 undistort_pixels, undistortion_map)
from lab.geometry.homogeneous import apply_homography, from_homogeneous, hartley_normalization, to_homogeneous
from lab.geometry.rotations import (look_at, matrix_to_rotvec, nearest_rotation, rotation_angle_deg,
                                    rotvec_to_matrix, skew, so3_left_jacobian)

__all__ = ["DISTORTION_NAMES", "apply_homography", "as_distortion", "as_intrinsics", "distort",
           "distort_components", "distort_with_jacobians", "from_homogeneous", "hartley_normalization",
           "look_at", "matrix_to_rotvec", "nearest_rotation", "normalized_to_pixels",
           "optimal_new_camera_matrix", "pixels_to_normalized", "project", "project_points",
           "rotation_angle_deg", "rotvec_to_matrix", "skew", "so3_left_jacobian", "to_homogeneous",
           "transform_points", "undistort", "undistort_pixels", "undistortion_map"]
