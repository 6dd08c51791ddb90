"""Comparing the SfM steps' cameras with the truth: a similarity alignment (Umeyama 1991,
:func:`lab.geometry.alignment.umeyama`), then pose errors.

A reconstruction is known only up to a similarity (rotation, translation, scale), so the estimated
cameras are first mapped onto the true ones (:func:`align_poses`); then the rotation error in
degrees and the camera-centre error relative to the size of the camera path (:func:`pose_errors`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from lab.geometry.alignment import umeyama
from lab.geometry.rotations import nearest_rotation, rotation_angle_deg


def align_poses(R_est: np.ndarray, t_est: np.ndarray, R_true: np.ndarray,
                t_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map estimated cameras into the true world by a similarity: returns ``(R_aligned, centers_aligned)``.

    Umeyama on the camera centres when they span a plane or a volume; on a line (a forward path) the
    rotation about the line is not determined by the centres, so the rotation is the chordal mean
    of ``R_true_i^T R_est_i`` and the scale and offset come from the centres by least squares.
    """
    C_est = -np.einsum("nji,nj->ni", R_est, t_est)
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    spread = np.linalg.svd(C_true - C_true.mean(axis=0), compute_uv=False)
    if len(C_true) >= 3 and spread[1] > 1e-3 * max(spread[0], 1e-12):
        s, Q, d = umeyama(C_est, C_true)
    else:
        Q = nearest_rotation(np.sum(np.swapaxes(R_true, 1, 2) @ R_est, axis=0))
        a = (C_est - C_est.mean(axis=0)) @ Q.T
        b = C_true - C_true.mean(axis=0)
        s = float(np.sum(a * b) / max(np.sum(a * a), 1e-300))
        d = C_true.mean(axis=0) - s * Q @ C_est.mean(axis=0)
    return R_est @ Q.T, s * C_est @ Q.T + d


def pose_errors(R_est: np.ndarray, t_est: np.ndarray, R_true: np.ndarray, t_true: np.ndarray,
                scene_size: float) -> dict[str, float]:
    """Rotation error (deg) and camera-centre error (fraction of ``scene_size``) after :func:`align_poses`."""
    R_aligned, C_aligned = align_poses(R_est, t_est, R_true, t_true)
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    rotation = rotation_angle_deg(R_aligned, R_true)
    center = np.linalg.norm(C_aligned - C_true, axis=1) / max(float(scene_size), 1e-12)
    return {"rotation_error_deg": float(rotation.mean()), "rotation_error_max_deg": float(rotation.max()),
            "center_error_rel": float(center.mean()), "center_error_max_rel": float(center.max())}


def registered_pose_errors(poses: np.ndarray, registered: np.ndarray,
                           truth: dict[str, Any]) -> dict[str, float]:
    """:func:`pose_errors` of the registered views of ``poses`` ``(V, 3, 4)`` (none with fewer than two)."""
    reg = np.flatnonzero(registered)
    if len(reg) < 2:
        return {}
    return pose_errors(poses[reg, :, :3], poses[reg, :, 3], truth["R"][reg], truth["t"][reg],
                       truth.get("scene_size", 1.0))


def evaluate_model(name: str) -> Callable[[dict[str, Any], dict[str, Any]], dict[str, float]]:
    """An evaluation of the registered cameras of the model in state ``name``
    (:func:`registered_pose_errors`)."""

    def evaluate(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
        if not truth or "R" not in truth or name not in state:
            return {}
        model = state[name]
        return registered_pose_errors(model.poses, model.registered, truth)

    evaluate.__name__ = f"evaluate_{name}"
    return evaluate


def evaluate_initial(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Rotation and direction-of-translation error of the initial pair against the truth."""
    if not truth or "R" not in truth or "initial_pose" not in state:
        return {}
    a, b = (int(v) for v in state["initial_pair"])
    R_rel = truth["R"][b] @ truth["R"][a].T
    t_rel = truth["t"][b] - R_rel @ truth["t"][a]
    pose = state["initial_pose"]
    cosine = float(pose[:, 3] @ t_rel / (np.linalg.norm(pose[:, 3]) * np.linalg.norm(t_rel)))
    return {"rotation_error_deg": float(rotation_angle_deg(pose[:, :3], R_rel)),
            "translation_direction_error_deg": float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))}
