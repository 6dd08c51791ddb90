"""lab.data.two_view: synthetic correspondences with exact truth.

The rendered pair and the photo loader of the epipolar module are tested in
tests/modules/test_epipolar_datasets.py.
"""

import numpy as np
import pytest

from lab.core import ImageSet, InvalidValue, Points2D
from lab.data.two_view import correspondences, relative_pose
from lab.geometry.camera import project_points
from lab.geometry.rotations import rotation_angle_deg
from lab.geometry.two_view import fundamental_from_pose


def _algebraic(F, x1, x2):
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    return np.sum(h2 * (h1 @ F.T), axis=1)


@pytest.fixture(scope="module")
def clean():
    return correspondences(num_points=200, noise_px=0.0, outlier_rate=0.0, seed=3)


# --- relative_pose / fundamental_from_pose ----------------------------------------------------------
def test_relative_pose_has_the_baseline_and_looks_at_the_scene():
    R, t = relative_pose(2.0, 5.0, np.random.default_rng(0))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert np.linalg.norm(t) == pytest.approx(2.0)
    centre = R @ np.array([0.0, 0.0, 5.0]) + t  # the scene centre in camera 2
    assert centre[2] > 0 and np.hypot(centre[0], centre[1]) / centre[2] < np.tan(np.radians(4.0))
    R0, t0 = relative_pose(0.0, 5.0, np.random.default_rng(0))
    assert np.linalg.norm(t0) == 0.0 and rotation_angle_deg(R0, np.eye(3)) > 0.5  # a pure rotation


def test_fundamental_from_pose_satisfies_the_epipolar_constraint(clean):
    truth = clean.truth
    F = fundamental_from_pose(truth["K1"], truth["K2"], truth["R"], truth["t"])
    assert np.linalg.norm(F) == pytest.approx(1.0)
    assert np.linalg.matrix_rank(F, tol=1e-10) == 2
    residual = _algebraic(F, truth["x1_exact"], truth["x2_exact"])
    assert np.abs(residual).max() < 1e-12


# --- correspondences --------------------------------------------------------------------------------
def test_correspondences_state_and_truth(clean):
    state, truth = clean.state, clean.truth
    assert set(state) == {"images", "K1", "K2", "keypoints", "descriptors", "matches", "x1", "x2"}
    assert isinstance(state["images"], ImageSet) and len(state["images"]) == 2
    assert state["images"][0].pixels.shape == (480, 640, 3)
    assert state["x1"].shape == state["x2"].shape == (200, 2)
    assert state["descriptors"].shape == (400, 128) and state["descriptors"].dtype == np.float32
    keypoints = state["keypoints"]
    assert isinstance(keypoints, Points2D) and keypoints.image == "images"
    np.testing.assert_array_equal(keypoints.view, np.repeat([0, 1], 200))
    np.testing.assert_array_equal(keypoints.xy[state["matches"][:, 0]], state["x1"])
    np.testing.assert_array_equal(keypoints.xy[state["matches"][:, 1]], state["x2"])
    np.testing.assert_allclose(state["K1"], [[600, 0, 319.5], [0, 600, 239.5], [0, 0, 1]])
    assert set(truth) >= {"K1", "K2", "R", "t", "F", "E", "points3d", "x1_exact", "x2_exact", "outliers",
                          "keypoint_track"}
    np.testing.assert_allclose(state["x1"], truth["x1_exact"])  # no noise
    exact2 = project_points(truth["points3d"], truth["K2"], None, truth["R"], truth["t"])
    np.testing.assert_allclose(exact2, truth["x2_exact"], atol=1e-9)
    in_camera2 = truth["points3d"] @ truth["R"].T + truth["t"]
    assert np.all(truth["points3d"][:, 2] > 0) and np.all(in_camera2[:, 2] > 0)
    for x in (state["x1"], state["x2"]):
        assert x[:, 0].min() >= 4 and x[:, 0].max() <= 635 and x[:, 1].min() >= 4 and x[:, 1].max() <= 475


def test_correspondences_noise_and_outliers_as_asked():
    loaded = correspondences(num_points=2000, noise_px=0.7, outlier_rate=0.25, seed=4)
    state, truth = loaded.state, loaded.truth
    outliers = truth["outliers"]
    assert outliers.sum() == 500
    error = np.concatenate([state["x1"] - truth["x1_exact"],
                            state["x2"][~outliers] - truth["x2_exact"][~outliers]])
    assert error.std() == pytest.approx(0.7, rel=0.05) and abs(error.mean()) < 0.05
    lines = np.column_stack([truth["x1_exact"], np.ones(2000)]) @ truth["F"].T
    signed = np.sum(lines[:, :2] * state["x2"], axis=1) + lines[:, 2]
    distance = np.abs(signed) / np.hypot(lines[:, 0], lines[:, 1])
    assert distance[outliers].min() > 10.0  # every outlier is far from its epipolar line
    np.testing.assert_array_equal(truth["keypoint_track"][2000:] == -1, outliers)


def test_correspondences_are_reproducible_and_follow_the_seed():
    a, b, c = (correspondences(num_points=50, seed=s) for s in (1, 1, 2))
    np.testing.assert_array_equal(a.state["x2"], b.state["x2"])
    assert not np.allclose(a.state["x2"], c.state["x2"])


def test_correspondences_descriptors_pair_each_match():
    state = correspondences(num_points=300, seed=5).state
    d = state["descriptors"].astype(np.float64)
    distance = np.linalg.norm(d[:300, None] - d[None, 300:], axis=2)
    np.testing.assert_array_equal(np.argmin(distance, axis=1), np.arange(300))
    second = np.sort(distance, axis=1)[:, 1]
    assert np.all(np.diag(distance) < 0.5 * second)  # passes any ratio test above 0.5


@pytest.mark.parametrize("structure", ["plane", "line"])
def test_degenerate_structures(structure):
    points = correspondences(num_points=100, structure=structure, seed=6).truth["points3d"]
    centred = points - points.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    if structure == "plane":
        assert singular[2] < 1e-9 * singular[0] and singular[1] > 0.1 * singular[0]
    else:
        assert singular[1] < 1e-9 * singular[0]


def test_zero_baseline_is_a_pure_rotation():
    loaded = correspondences(num_points=100, baseline=0.0, noise_px=0.0, outlier_rate=0.0, seed=7)
    truth = loaded.truth
    assert np.linalg.norm(truth["t"]) == 0 and not np.any(truth["F"])
    H = truth["K2"] @ truth["R"] @ np.linalg.inv(truth["K1"])
    mapped = np.column_stack([loaded.state["x1"], np.ones(100)]) @ H.T
    np.testing.assert_allclose(mapped[:, :2] / mapped[:, 2:], loaded.state["x2"], atol=1e-8)


def test_dot_images_show_the_points():
    loaded = correspondences(num_points=20, outlier_rate=0.0, noise_px=0.0, seed=8)
    image, x1 = loaded.state["images"][0], loaded.state["x1"]
    colors = loaded.state["keypoints"].colors[:20]
    at = image.pixels[np.round(x1[:, 1]).astype(int), np.round(x1[:, 0]).astype(int)]
    np.testing.assert_allclose(at, colors, atol=0.02)


@pytest.mark.parametrize("options, field", [(dict(num_points=5), "num_points"), (dict(cx=700.0), "cx"),
                                            (dict(depth_range=10.0), "depth_range")])
def test_correspondences_errors(options, field):
    with pytest.raises(InvalidValue) as error:
        correspondences(**options)
    assert error.value.field == field
