"""lab/modules/sfm_basics.py: the teaching pipeline of lesson 04 (linear / non-linear PnP and triangulation,
the bundle-adjustment sparsity pattern, bundle adjustment), against the truth, OpenCV and bad input."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from lab.core import InvalidValue, Points2D, open_session
from lab.core.codecs import to_json
from lab.geometry.bundle_adjustment import bundle_sparsity
from lab.geometry.rotations import rotation_angle_deg
from lab.modules import MODULES
from lab.modules.sfm_basics import (PIPELINE, bundle_adjust_scene, estimate_poses_linear, jacobian_sparsity,
                                    refine_points_nonlinear, refine_poses, synthetic,
                                    triangulate_points_linear)

EXACT = {"noise_px": 0.0, "map_noise": 0.0}


def scene(seed: int = 3, **options):
    return synthetic(**{"num_points": 40, "num_views": 5, **options, "seed": seed})


def poses_of(truth) -> np.ndarray:
    return np.concatenate([truth["R"], truth["t"][:, :, None]], axis=2)


@pytest.fixture(scope="module")
def noisy_run():
    session = open_session(PIPELINE, "synthetic", {"seed": 5}, seed=5)
    session.run_until("bundle_adjust_scene")
    return session


# --- the dataset -----------------------------------------------------------------------------------
def test_dataset_shapes_and_visibility():
    loaded = scene(num_points=50, num_views=6, visibility=0.6)
    state, truth = loaded.state, loaded.truth
    obs = state["observations"]
    assert isinstance(obs, Points2D) and obs.view is not None and obs.ids is not None
    assert state["points3d"].shape == (50, 3) and state["K"].shape == (3, 3)
    assert truth["R"].shape == (6, 3, 3) and truth["t"].shape == (6, 3) and truth["X"].shape == (50, 3)
    assert np.array_equal(state["camera_indices"], obs.view) and np.array_equal(state["point_indices"],
                                                                                obs.ids)
    assert state["num_cameras"] == 6 and state["num_points"] == 50
    seen = np.zeros((6, 50), dtype=int)
    np.add.at(seen, (obs.view, obs.ids), 1)
    assert seen.max() == 1  # a camera sees a point at most once
    assert seen.sum(axis=0).min() >= 2 and seen.sum(axis=1).min() >= 12
    assert 0.45 < seen.mean() < 0.75  # about the visibility asked for


def test_dataset_exact_pixels_are_the_projections_and_noise_is_seeded():
    loaded = scene(**EXACT)
    obs, truth = loaded.state["observations"], loaded.truth
    assert np.allclose(obs.xy, truth["pixels"], atol=1e-9)
    assert np.array_equal(loaded.state["points3d"], truth["X"])
    for v in range(5):  # every camera has the points in front of it and inside the image
        mine = obs.view == v
        Xc = truth["X"][obs.ids[mine]] @ truth["R"][v].T + truth["t"][v]
        assert np.all(Xc[:, 2] > 0)
        assert np.all((obs.xy[mine] > 0) & (obs.xy[mine] < (640, 480)))
    noisy_a, noisy_b, other = scene(noise_px=1.0), scene(noise_px=1.0), scene(seed=4, noise_px=1.0)
    assert np.array_equal(noisy_a.state["observations"].xy, noisy_b.state["observations"].xy)
    residual = noisy_a.state["observations"].xy - noisy_a.truth["pixels"]
    assert 0.8 < residual.std() < 1.2
    assert not np.array_equal(other.truth["X"], noisy_a.truth["X"])


def test_dataset_outliers_replace_a_share_of_observations():
    loaded = scene(noise_px=0.0, outlier_rate=0.3)
    off = np.linalg.norm(loaded.state["observations"].xy - loaded.truth["pixels"], axis=1) > 1e-6
    assert 0.15 < off.mean() < 0.45


def test_some_camera_has_the_world_origin_behind_it():
    """The lesson relies on it: normalizing P by P[2, 3] then flips some camera."""
    for seed in range(5):
        truth = synthetic(num_views=6, seed=seed).truth
        assert np.any(truth["t"][:, 2] < 0) and np.any(truth["t"][:, 2] > 0)


# --- linear and non-linear PnP ------------------------------------------------------------------------
def test_linear_pnp_recovers_exact_poses():
    loaded = scene(**EXACT)
    poses = estimate_poses_linear(loaded.state["points3d"], loaded.state["observations"], loaded.state["K"])
    assert poses.shape == (5, 3, 4)
    assert np.allclose(poses, poses_of(loaded.truth), atol=1e-8)
    assert np.allclose(np.linalg.det(poses[:, :, :3]), 1.0)


def test_linear_pnp_does_not_depend_on_the_order_of_observations():
    loaded = scene(noise_px=1.0)
    obs = loaded.state["observations"]
    order = np.random.default_rng(0).permutation(len(obs))
    shuffled = Points2D(obs.xy[order], view=obs.view[order], ids=obs.ids[order])
    a = estimate_poses_linear(loaded.state["points3d"], obs, loaded.state["K"])
    b = estimate_poses_linear(loaded.state["points3d"], shuffled, loaded.state["K"])
    assert np.allclose(a, b, atol=1e-9)


def test_refined_poses_match_opencv_iterative_pnp():
    """With the plain squared loss the refinement minimizes what cv2.solvePnP(SOLVEPNP_ITERATIVE) does."""
    loaded = scene(noise_px=1.0, map_noise=0.0)
    state = loaded.state
    linear = estimate_poses_linear(state["points3d"], state["observations"], state["K"])
    result = refine_poses(linear, state["points3d"], state["observations"], state["K"], state["image_size"],
                          loss="linear")
    obs = state["observations"]
    for v in range(5):
        mine = obs.view == v
        ok, rvec, tvec = cv2.solvePnP(state["points3d"][obs.ids[mine]], obs.xy[mine], state["K"], None,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        assert ok
        R_cv, _ = cv2.Rodrigues(rvec)
        assert rotation_angle_deg(result.poses[v, :, :3], R_cv) < 1e-3
        assert np.allclose(result.poses[v, :, 3], tvec.ravel(), atol=1e-4)
    assert result.rms_refined_px <= result.rms_linear_px
    assert result.points_behind_linear == 0 and result.orthonormality_linear < 1e-12
    angles = rotation_angle_deg(result.poses[:, :, :3], loaded.truth["R"])
    assert angles.max() < 0.5


def test_refine_poses_reports_a_start_that_is_not_a_rotation_and_still_returns_rotations():
    loaded = scene(noise_px=1.0)
    state = loaded.state
    linear = estimate_poses_linear(state["points3d"], state["observations"], state["K"])
    stretched = linear.copy()
    stretched[:, :, :3] *= 1.1
    result = refine_poses(stretched, state["points3d"], state["observations"], state["K"],
                          state["image_size"])
    assert result.orthonormality_linear > 0.2
    R = result.poses[:, :, :3]
    assert np.allclose(np.swapaxes(R, 1, 2) @ R, np.eye(3), atol=1e-9)
    flipped = -linear
    behind = refine_poses(flipped, state["points3d"], state["observations"], state["K"], state["image_size"])
    assert behind.points_behind_linear == len(state["observations"])


def test_linear_pnp_errors_name_the_problem():
    loaded = scene(**EXACT)
    state = loaded.state
    obs = state["observations"]
    few = obs.view != 2
    few[np.flatnonzero(obs.view == 2)[:5]] = True  # camera 2 keeps 5 points
    with pytest.raises(InvalidValue, match="camera 2 sees 5 known points"):
        estimate_poses_linear(state["points3d"], Points2D(obs.xy[few], view=obs.view[few], ids=obs.ids[few]),
                              state["K"])
    gap = obs.view != 1
    with pytest.raises(InvalidValue, match="without gaps"):
        estimate_poses_linear(state["points3d"], Points2D(obs.xy[gap], view=obs.view[gap], ids=obs.ids[gap]),
                              state["K"])
    with pytest.raises(InvalidValue, match="needs view"):
        estimate_poses_linear(state["points3d"], Points2D(obs.xy), state["K"])
    with pytest.raises(InvalidValue, match="3D points"):
        estimate_poses_linear(state["points3d"][:10], obs, state["K"])
    with pytest.raises(InvalidValue, match="K"):
        estimate_poses_linear(state["points3d"], obs, np.eye(4))


# --- linear and non-linear triangulation ----------------------------------------------------------------
def test_linear_triangulation_recovers_exact_points():
    loaded = scene(**EXACT)
    X = triangulate_points_linear(loaded.state["observations"], poses_of(loaded.truth), loaded.state["K"])
    assert X.shape == (40, 3)
    assert np.allclose(X, loaded.truth["X"], atol=1e-8)


def test_linear_triangulation_with_two_views_is_opencvs():
    loaded = scene(noise_px=1.0, num_views=2, visibility=1.0)
    obs, K, poses = loaded.state["observations"], loaded.state["K"], poses_of(loaded.truth)
    X = triangulate_points_linear(obs, poses, K)
    first, second = obs.view == 0, obs.view == 1
    assert np.array_equal(obs.ids[first], obs.ids[second])
    homogeneous = cv2.triangulatePoints(K @ poses[0], K @ poses[1], obs.xy[first].T, obs.xy[second].T)
    expected = (homogeneous[:3] / homogeneous[3]).T
    assert np.allclose(X[obs.ids[first]], expected, rtol=1e-7, atol=1e-7)


def test_non_linear_triangulation_lowers_the_error():
    loaded = scene(noise_px=1.0)
    obs, K, poses = loaded.state["observations"], loaded.state["K"], poses_of(loaded.truth)
    linear = triangulate_points_linear(obs, poses, K)
    refined = refine_points_nonlinear(linear, obs, poses, K, loaded.state["image_size"])
    assert refined.rms_refined_px < refined.rms_linear_px
    assert refined.points_behind_linear == 0
    model = refined.model
    assert np.sqrt(np.mean(np.sum((model.points - loaded.truth["X"]) ** 2, axis=1))) < 0.05
    # the model is the scene: the cameras given, every observation a keypoint of its point's track
    np.testing.assert_array_equal(model.poses, poses)
    kp, views, point = model.observations()
    np.testing.assert_array_equal(kp, np.arange(len(obs)))
    np.testing.assert_array_equal(views, obs.view)
    np.testing.assert_array_equal(point, obs.ids)
    assert model.registered.all() and np.all(model.K == K)
    Xc = np.einsum("mij,mj->mi", poses[obs.view, :, :3], model.points[obs.ids]) + poses[obs.view, :, 3]
    errors = np.linalg.norm(Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2] - obs.xy, axis=1)
    np.testing.assert_allclose(model.errors, np.bincount(obs.ids, errors) / np.bincount(obs.ids), rtol=1e-9)


def test_triangulation_errors_name_the_problem():
    loaded = scene(**EXACT)
    obs, K, poses = loaded.state["observations"], loaded.state["K"], poses_of(loaded.truth)
    lonely = np.flatnonzero(obs.ids == 0)
    keep = np.ones(len(obs), dtype=bool)
    keep[lonely[1:]] = False  # point 0 seen once
    with pytest.raises(InvalidValue, match="point 0 is seen by fewer than two cameras"):
        triangulate_points_linear(Points2D(obs.xy[keep], view=obs.view[keep], ids=obs.ids[keep]), poses, K)
    with pytest.raises(InvalidValue, match="there are 3 poses"):
        triangulate_points_linear(obs, poses[:3], K)
    with pytest.raises(InvalidValue, match=r"\[R \| t\]"):
        triangulate_points_linear(obs, poses[:, :, :3], K)
    twice = Points2D(np.vstack([obs.xy, obs.xy[:1]]), view=np.append(obs.view, obs.view[0]),
                     ids=np.append(obs.ids, obs.ids[0]))
    with pytest.raises(InvalidValue, match="same point twice"):
        triangulate_points_linear(twice, poses, K)


# --- the sparsity pattern and bundle adjustment ----------------------------------------------------------
def test_sparsity_known_answer():
    pattern = jacobian_sparsity(np.array([0, 1, 1]), np.array([1, 0, 1]), 2, 2)
    assert pattern.shape == (6, 18) and pattern.dtype == bool
    expected = np.zeros((6, 18), dtype=bool)
    for i, (c, p) in enumerate([(0, 1), (1, 0), (1, 1)]):
        expected[2 * i:2 * i + 2, 6 * c:6 * c + 6] = True
        expected[2 * i:2 * i + 2, 12 + 3 * p:12 + 3 * p + 3] = True
    assert np.array_equal(pattern, expected)


def test_sparsity_is_the_geometry_pattern_and_nine_entries_a_row():
    state = scene().state
    pattern = jacobian_sparsity(state["camera_indices"], state["point_indices"], state["num_cameras"],
                                state["num_points"])
    m = len(state["camera_indices"])
    assert pattern.shape == (2 * m, 6 * 5 + 3 * 40)
    assert np.all(pattern.sum(axis=1) == 9)
    reference = bundle_sparsity(state["camera_indices"], state["point_indices"], 5, 40).toarray()
    assert np.array_equal(pattern, reference.astype(bool))


def test_sparsity_errors_name_the_problem():
    with pytest.raises(InvalidValue, match="same length"):
        jacobian_sparsity(np.array([0, 1]), np.array([0]), 2, 2)
    with pytest.raises(InvalidValue, match="integers"):
        jacobian_sparsity(np.array([0.0, 1.0]), np.array([0, 1]), 2, 2)
    with pytest.raises(InvalidValue, match="num_points"):
        jacobian_sparsity(np.array([0, 1]), np.array([0, 1]), 2, 0)
    with pytest.raises(InvalidValue, match="camera_indices"):
        jacobian_sparsity(np.array([0, 2]), np.array([0, 1]), 2, 2)


def test_bundle_adjustment_lowers_the_error_and_a_wrong_pattern_does_worse(noisy_run):
    state, metrics = noisy_run.state, noisy_run.metrics["bundle_adjust_scene"]
    assert metrics["ba_improved"] and metrics["ba_rms_px"] < metrics["ba_rms_before_px"]
    assert metrics["sparsity_missing"] == 0 and metrics["sparsity_extra"] == 0
    adjusted, model = state["adjusted_model"], state["model"]
    assert adjusted.poses.shape == state["poses"].shape and adjusted.points.shape == model.points.shape
    np.testing.assert_array_equal(model.poses, state["poses"])
    assert np.array_equal(adjusted.poses[0], state["poses"][0])  # the first camera is held
    assert adjusted.errors.mean() < model.errors.mean()
    pattern = state["sparsity"]
    no_points = pattern.copy()
    no_points[:, 6 * state["num_cameras"]:] = False
    without = bundle_adjust_scene(model, no_points)
    assert without.sparsity_missing == 2 * len(state["observations"]) * 3 and without.sparsity_extra == 0
    assert without.ba_rms_px > 1.05 * metrics["ba_rms_px"]
    dense = bundle_adjust_scene(model, np.ones_like(pattern), max_iterations=5)
    assert dense.sparsity_extra == pattern.size - pattern.sum()
    assert dense.ba_rms_px < dense.ba_rms_before_px  # right derivatives, only more evaluations


def test_bundle_adjustment_errors_name_the_problem(noisy_run):
    state = noisy_run.state
    model = state["model"]
    with pytest.raises(InvalidValue, match="expected shape"):
        bundle_adjust_scene(model, state["sparsity"].T)
    fewer = dataclasses.replace(model, points=model.points[:5], point_tracks=model.point_tracks[:5],
                                colors=model.colors[:5],
                                errors=model.errors[:5])  # the pattern's points are not all there
    with pytest.raises(InvalidValue, match=r"expected shape .* per point"):
        bundle_adjust_scene(fewer, state["sparsity"])
    with pytest.raises(InvalidValue, match="SparseModel"):
        bundle_adjust_scene(state["points3d"], state["sparsity"])


# --- the pipeline as a whole ----------------------------------------------------------------------------
def test_pipeline_is_deterministic_encodable_and_not_registered(noisy_run):
    assert "sfm_basics" not in MODULES
    again = open_session(PIPELINE, "synthetic", {"seed": 5}, seed=5)
    again.run_until("bundle_adjust_scene")
    assert np.array_equal(again.state["adjusted_model"].points, noisy_run.state["adjusted_model"].points)
    assert again.metrics == noisy_run.metrics
    for value in noisy_run.state.values():
        json.dumps(to_json(value))  # every state value has a JSON form
    metrics = noisy_run.metrics
    assert metrics["refine_poses"]["rms_refined_px"] < metrics["refine_poses"]["rms_linear_px"]
    linear_error = metrics["estimate_poses_linear"]["linear_rotation_error_deg"]
    assert metrics["refine_poses"]["rotation_error_deg"] < linear_error
    points = metrics["refine_points_nonlinear"]
    assert points["rms_refined_px"] <= points["rms_linear_px"]
    json.dumps(metrics)
