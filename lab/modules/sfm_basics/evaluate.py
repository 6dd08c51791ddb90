"""The lesson pipeline's comparisons with the truth: pose errors (deg, m) and point errors (m) per stage."""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.geometry.rotations import nearest_rotation, rotation_angle_deg


def _pose_errors(poses: np.ndarray, truth: dict[str, Any], prefix: str = "") -> dict[str, float]:
    if "R" not in truth or np.shape(poses)[0] != len(truth["R"]):
        return {}
    poses = np.asarray(poses, dtype=np.float64)
    R_true, t_true = np.asarray(truth["R"]), np.asarray(truth["t"])
    angles = rotation_angle_deg(nearest_rotation(poses[:, :, :3]), R_true)
    centers = -np.einsum("vji,vj->vi", poses[:, :, :3], poses[:, :, 3])
    centers_true = -np.einsum("vji,vj->vi", R_true, t_true)
    center_errors = np.linalg.norm(centers - centers_true, axis=1)
    return {f"{prefix}rotation_error_deg": float(angles.max()),
            f"{prefix}center_error_m": float(center_errors.max())}


def evaluate_poses_linear(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Largest rotation angle (deg) and camera-centre distance (m) of the linear poses from the truth."""
    return _pose_errors(state["poses_linear"], truth, "linear_")


def evaluate_poses(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Largest rotation angle (deg) and camera-centre distance (m) of the refined poses from the truth."""
    return _pose_errors(state["poses"], truth)


def _point_error(points: np.ndarray, truth: dict[str, Any], name: str) -> dict[str, float]:
    if "X" not in truth or np.shape(points) != np.shape(truth["X"]):
        return {}
    return {name: float(np.sqrt(np.mean(np.sum((np.asarray(points) - truth["X"]) ** 2, axis=1))))}


def evaluate_points_linear(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """RMS distance (m) of the linear points from the true points."""
    return _point_error(state["points_linear"], truth, "linear_point_error_m")


def evaluate_points(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """RMS distance (m) of the refined points from the true points."""
    return _point_error(state["model"].points, truth, "point_error_m")


def evaluate_bundle(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Rotation and centre errors of the adjusted cameras (the first is held, so the frame is the world's
    up to a small scale drift); RMS distance of the adjusted points from the truth."""
    adjusted = state["adjusted_model"]
    metrics = _pose_errors(adjusted.poses, truth, "ba_")
    metrics.update(_point_error(adjusted.points, truth, "ba_point_error_m"))
    return metrics
