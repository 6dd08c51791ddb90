"""The evaluations of calibration: each step's outputs against the synthetic truth (run after the step).

``truth`` is empty on real photos: then only what needs no truth is measured (the homographies'
transfer error). Every function is ``evaluate(state, truth) -> metrics``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.core import Points2D
from lab.core.pipeline import Evaluation
from lab.geometry.homogeneous import apply_homography
from lab.geometry.rotations import rotation_angle_deg
from lab.modules.calibration.observations import views_of


def intrinsic_errors(K: np.ndarray, truth: dict[str, Any]) -> dict[str, float]:
    """Relative errors of fx, fy, cx, cy and the absolute error of the skew against the true ``K``."""
    T = np.asarray(truth["K"])
    return {"fx_rel_error": abs(K[0, 0] - T[0, 0]) / T[0, 0],
            "fy_rel_error": abs(K[1, 1] - T[1, 1]) / T[1, 1],
            "cx_rel_error": abs(K[0, 2] - T[0, 2]) / T[0, 2],
            "cy_rel_error": abs(K[1, 2] - T[1, 2]) / T[1, 2],
            "skew_abs_error": abs(K[0, 1] - T[0, 1])}


def pose_errors(R: np.ndarray, t: np.ndarray, views: np.ndarray, truth: dict[str, Any]) -> dict[str, float]:
    """Mean and largest rotation error (degrees) and mean relative translation error of the used views."""
    R_true = np.asarray(truth["rotations"])[views]
    t_true = np.asarray(truth["translations"])[views]
    angles = rotation_angle_deg(R, R_true)
    rel = np.linalg.norm(t - t_true, axis=1) / np.linalg.norm(t_true, axis=1)
    return {"rotation_error_deg": float(angles.mean()), "rotation_error_max_deg": float(angles.max()),
            "translation_rel_error": float(rel.mean())}


def evaluate_homographies(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``transfer_rms_px``: RMS distance from the detected corners to the board mapped by H (no truth)."""
    corners, board_points, H = state["corners"], state["board_points"], state["homographies"]
    _, position = views_of(corners)
    mapped = apply_homography(np.asarray(H)[position], board_points[corners.ids][:, None, :2])[:, 0]
    return {"transfer_rms_px": float(np.sqrt(np.mean(np.sum((mapped - corners.xy) ** 2, axis=1))))}


def evaluate_intrinsics(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Relative errors of ``K_init`` against the true ``K``."""
    return intrinsic_errors(np.asarray(state["K_init"]), truth) if "K" in truth else {}


def evaluate_extrinsics(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Rotation angle error (degrees) and relative translation error of the closed-form poses."""
    if "rotations" not in truth:
        return {}
    return pose_errors(state["R_init"], state["t_init"], views_of(state["corners"])[0], truth)


def evaluate_distortion(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Absolute errors of the linear ``k1, k2``."""
    if "dist" not in truth:
        return {}
    d, T = np.asarray(state["dist_init"]), np.asarray(truth["dist"])
    return {"k1_abs_error": abs(d[0] - T[0]), "k2_abs_error": abs(d[1] - T[1])}


def evaluate_refinement(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Errors of the refined intrinsics, distortion and poses; ``truth_rms_px``: RMS distance between
    the reprojected corners and the exact (noise-free) projections."""
    if "K" not in truth:
        return {}
    out = intrinsic_errors(np.asarray(state["K"]), truth)
    d, T = np.asarray(state["dist"]), np.asarray(truth["dist"])
    names = ("k1", "k2", "p1", "p2", "k3")
    out.update({f"{name}_abs_error": abs(d[i] - T[i]) for i, name in enumerate(names)})
    out.update(pose_errors(state["rotations"], state["translations"], views_of(state["corners"])[0], truth))
    if "corners" in truth:
        out["truth_rms_px"] = _truth_rms(state["reprojected"], truth["corners"])
    return out


def _truth_rms(reprojected: Points2D, exact: Points2D) -> float:
    """RMS distance between reprojected corners and the exact projections of the same (view, id)."""
    exact_view, exact_ids = np.asarray(exact.view), np.asarray(exact.ids)
    n = int(exact_ids.max()) + 1
    lookup = {int(v) * n + int(i): k for k, (v, i) in enumerate(zip(exact_view, exact_ids, strict=True))}
    pairs = zip(np.asarray(reprojected.view), np.asarray(reprojected.ids), strict=True)
    index = np.array([lookup[int(v) * n + int(i)] for v, i in pairs])
    diff = reprojected.xy - exact.xy[index]
    return float(np.sqrt(np.mean(np.sum(diff * diff, axis=1))))


#: The evaluation run after each step (``Pipeline.build(evaluations=...)``).
EVALUATIONS: dict[str, Evaluation] = {
    "estimate_homographies": evaluate_homographies, "estimate_intrinsics": evaluate_intrinsics,
    "estimate_extrinsics": evaluate_extrinsics, "estimate_distortion": evaluate_distortion,
    "refine_calibration": evaluate_refinement}

__all__ = ["EVALUATIONS", "evaluate_distortion", "evaluate_extrinsics", "evaluate_homographies",
           "evaluate_intrinsics", "evaluate_refinement", "intrinsic_errors", "pose_errors"]
