"""Comparisons with the truth, run after a step: the metrics a dataset with ground truth adds (truth may be
empty).

The truth (``Session.truth``) is never a step input; these functions read it beside the state the steps
wrote, and their numbers join the step's metrics (:data:`EVALUATIONS`, by step name).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.core import InvalidValue
from lab.core.pipeline import Evaluation
from lab.geometry.homogeneous import to_homogeneous
from lab.geometry.rotations import rotation_angle_deg
from lab.modules.epipolar._checks import inliers_or_all, rotation_problem
from lab.modules.epipolar.distances import sampson_distance
from lab.modules.epipolar.fundamental import numerical_rank


def _correct_matches(state: dict[str, Any], truth: dict[str, Any],
                     tolerance_px: float = 3.0) -> np.ndarray | None:
    """Which matches are right, ``(M,)`` bool, from the truth (the generator's tracks, or depth maps)."""
    matches = state.get("matches")
    if "keypoint_track" in truth and matches is not None:
        track = np.asarray(truth["keypoint_track"])
        if len(track) == len(state["keypoints"]):
            a, b = track[matches[:, 0]], track[matches[:, 1]]
            return (a == b) & (a >= 0)
    if "depth" in truth and "x1" in state:
        points = _true_points(state, truth)
        projected = points @ truth["R"].T + truth["t"]
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = projected @ truth["K2"].T
            pixels = pixels[:, :2] / pixels[:, 2:]
        return np.linalg.norm(pixels - state["x2"], axis=1) <= tolerance_px
    return None


def _true_points(state: dict[str, Any], truth: dict[str, Any]) -> np.ndarray:
    """The true 3D point (camera 1 frame) behind each match's ``x1``, ``(M, 3)`` (NaN where unknown)."""
    x1 = np.asarray(state["x1"])
    if "keypoint_track" in truth and "points3d" in truth and "matches" in state:
        track = np.asarray(truth["keypoint_track"])[state["matches"][:, 0]]
        points = np.full((len(x1), 3), np.nan)
        points[track >= 0] = truth["points3d"][track[track >= 0]]
        return points
    depth = np.asarray(truth["depth"])[0]
    cols = np.clip(np.round(x1[:, 0]).astype(int), 0, depth.shape[1] - 1)
    rows = np.clip(np.round(x1[:, 1]).astype(int), 0, depth.shape[0] - 1)
    z = depth[rows, cols]
    z = np.where(np.isfinite(z) & (z > 0), z, np.nan)
    rays = to_homogeneous(x1) @ np.linalg.inv(truth["K1"]).T
    return rays * z[:, None]


def _f_metrics(F: np.ndarray, state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    out: dict[str, float] = {"rank_of_F": numerical_rank(F)}
    mask = inliers_or_all(state.get("inliers"), len(state["x1"]))
    distances = sampson_distance(F, state["x1"][mask], state["x2"][mask])
    out["sampson_rms_px"] = float(np.sqrt(np.mean(distances**2)))
    if "F" in truth and np.any(truth["F"]):
        a, b = F / np.linalg.norm(F), truth["F"] / np.linalg.norm(truth["F"])
        out["f_error"] = float(min(np.linalg.norm(a - b), np.linalg.norm(a + b)))
    if "x1_exact" in truth:
        exact = sampson_distance(F, truth["x1_exact"], truth["x2_exact"])
        out["truth_sampson_rms_px"] = float(np.sqrt(np.mean(exact**2)))
    return out


def evaluate_matches(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``match_precision``: the fraction of the matches that are right (with truth)."""
    correct = _correct_matches(state, truth)
    if correct is None or len(correct) == 0:
        return {}
    return {"match_precision": float(correct.mean()), "correct_matches": int(correct.sum())}


def evaluate_fundamental(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``rank_of_F``, ``sampson_rms_px`` (inliers, or all matches); with truth ``f_error`` (distance
    between the unit-norm F and the true one, sign aligned), ``truth_sampson_rms_px`` (how far the
    exact, noise-free correspondences are from F), and after RANSAC ``inlier_precision`` /
    ``inlier_recall`` against the right matches."""
    F = np.asarray(state["F"])
    out = _f_metrics(F, state, truth)
    correct = _correct_matches(state, truth)
    if correct is not None and "inliers" in state and state.get("inliers") is not None:
        inliers = np.asarray(state["inliers"], dtype=bool)
        if len(inliers) == len(correct):
            out["inlier_precision"] = float(np.sum(inliers & correct) / max(inliers.sum(), 1))
            out["inlier_recall"] = float(np.sum(inliers & correct) / max(correct.sum(), 1))
    return out


def evaluate_fundamental_8point(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """As :func:`evaluate_fundamental`, over all matches (the 8-point step uses them all)."""
    everything = {k: v for k, v in state.items() if k != "inliers"}
    return _f_metrics(np.asarray(state["F"]), everything, truth)


def evaluate_essential(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``essential_singular_ratio``: sigma2 / sigma1 of ``K2^T F K1`` before the projection (1 for an
    exact F and K); with truth ``e_error`` (distance to the true unit-norm-t E, sign aligned)."""
    out: dict[str, float] = {}
    if state.get("K1") is not None and state.get("K2") is not None:
        product = np.asarray(state["K2"]).T @ state["F"] @ np.asarray(state["K1"])
        singular = np.linalg.svd(product, compute_uv=False)
        out["essential_singular_ratio"] = float(singular[1] / singular[0])
    if "E" in truth and np.any(truth["E"]):
        a = state["E"] / np.linalg.norm(state["E"])
        b = truth["E"] / np.linalg.norm(truth["E"])
        out["e_error"] = float(min(np.linalg.norm(a - b), np.linalg.norm(a + b)))
    return out


def _rotation_and_direction_errors(R: np.ndarray, t: np.ndarray, truth: dict[str, Any], *,
                                   what: str = "pose") -> dict[str, float]:
    """``rotation_error_deg`` and ``translation_direction_error_deg`` against the truth; an ``R`` that is no
    rotation (a reflection) has no rotation error: :class:`InvalidValue` names its value."""
    problem = rotation_problem(np.asarray(R, dtype=np.float64))
    if problem:
        raise InvalidValue(what, f"{problem}, so its angle to the true rotation is not defined")
    out = {"rotation_error_deg": float(rotation_angle_deg(R, truth["R"]))}
    norm = np.linalg.norm(truth["t"])
    if norm > 0:
        cosine = float(np.dot(t / np.linalg.norm(t), truth["t"] / norm))
        out["translation_direction_error_deg"] = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
    return out


def evaluate_candidates(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``best_candidate_rotation_error_deg``: the candidate rotation nearest the true one (of
    those that are rotations; ``reflections``: how many of the four have det R = -1)."""
    if "R" not in truth:
        return {}
    rotations = np.asarray(state["candidates"], dtype=np.float64)[:, :, :3]
    proper = np.array([rotation_problem(R) is None for R in rotations])
    out: dict[str, float] = {"reflections": int(np.sum(np.linalg.det(rotations) < 0))}
    if proper.any():
        angles = rotation_angle_deg(rotations[proper], np.broadcast_to(truth["R"], (int(proper.sum()), 3, 3)))
        out["best_candidate_rotation_error_deg"] = float(np.min(angles))
    return out


def evaluate_pose(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``rotation_error_deg`` and ``translation_direction_error_deg`` (t against the true t)."""
    if "R" not in truth:
        return {}
    pose = np.asarray(state["pose"])
    return _rotation_and_direction_errors(pose[:, :3], pose[:, 3], truth)


def evaluate_refined_pose(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``rotation_error_deg`` and ``translation_direction_error_deg`` of the refined R and t."""
    if "R" not in truth:
        return {}
    return _rotation_and_direction_errors(np.asarray(state["R"]), np.asarray(state["t"]), truth, what="R")


def _point_errors(points: np.ndarray, state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Median relative 3D error of the points, the reconstruction scaled by the true baseline length."""
    if "R" not in truth or not np.linalg.norm(truth["t"]) > 0:
        return {}
    mask = inliers_or_all(state.get("inliers"), len(state["x1"]))
    true_points = _true_points(state, truth)[mask]
    points = np.asarray(points) * np.linalg.norm(truth["t"])
    known = np.all(np.isfinite(true_points), axis=1) & np.all(np.isfinite(points), axis=1)
    correct = _correct_matches(state, truth)
    if correct is not None:
        known &= correct[mask]
    if not known.any():
        return {}
    relative = (np.linalg.norm(points[known] - true_points[known], axis=1)
                / np.linalg.norm(true_points[known], axis=1))
    return {"point_rel_error_median": float(np.median(relative))}


def evaluate_triangulation(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``point_rel_error_median`` of the DLT points (scaled by the true baseline)."""
    return _point_errors(state["points3d_dlt"], state, truth)


def evaluate_refinement(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``point_rel_error_median`` of the refined points (scaled by the true baseline)."""
    mask = inliers_or_all(state.get("inliers"), len(state["x1"]))
    points = np.full((int(mask.sum()), 3), np.nan)
    finite = np.all(np.isfinite(np.asarray(state["points3d_dlt"])), axis=1)
    points[finite] = state["points3d"].xyz
    return _point_errors(points, state, truth)


#: The evaluation of each step that has one, by step name (``Pipeline.build(evaluations=...)``).
EVALUATIONS: dict[str, Evaluation] = {
    "match_features": evaluate_matches, "estimate_fundamental_8point": evaluate_fundamental_8point,
    "estimate_fundamental_ransac": evaluate_fundamental, "estimate_essential": evaluate_essential,
    "decompose_essential": evaluate_candidates, "recover_pose": evaluate_pose,
    "refine_pose": evaluate_refined_pose, "triangulate": evaluate_triangulation,
    "refine_points": evaluate_refinement}


__all__ = ["EVALUATIONS", "evaluate_candidates", "evaluate_essential", "evaluate_fundamental",
           "evaluate_fundamental_8point", "evaluate_matches", "evaluate_pose", "evaluate_refined_pose",
           "evaluate_refinement", "evaluate_triangulation"]
