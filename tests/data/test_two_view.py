"""lab.data.two_view: synthetic correspondences and rendered pairs with exact truth, and the photo-pair loader."""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.core import Image, ImageSet, InvalidValue, Points2D
from lab.data.two_view import (correspondences, fundamental_from_pose, photos, read_k_file, relative_pose,
                               rendered)
from lab.geometry.camera import project_points
from lab.geometry.rotations import rotation_angle_deg

SAMPLES = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "opencv-samples"
LEUVEN_K = np.array([[651.4462353114224, 0.0, 376.27522319223914], [0.0, 653.7348054191838, 280.1106539526218],
                     [0.0, 0.0, 1.0]])


def _algebraic(F, x1, x2):
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    return np.sum(h2 * (h1 @ F.T), axis=1)


@pytest.fixture(scope="module")
def clean():
    return correspondences(num_points=200, noise_px=0.0, outlier_rate=0.0, seed=3)


@pytest.fixture(scope="module")
def small_render():
    return rendered(width=160, height=120, supersample=1, seed=1)


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
    assert np.all(truth["points3d"][:, 2] > 0) and np.all((truth["points3d"] @ truth["R"].T + truth["t"])[:, 2] > 0)
    for x in (state["x1"], state["x2"]):
        assert x[:, 0].min() >= 4 and x[:, 0].max() <= 635 and x[:, 1].min() >= 4 and x[:, 1].max() <= 475


def test_correspondences_noise_and_outliers_as_asked():
    loaded = correspondences(num_points=2000, noise_px=0.7, outlier_rate=0.25, seed=4)
    state, truth = loaded.state, loaded.truth
    outliers = truth["outliers"]
    assert outliers.sum() == 500
    error = np.concatenate([state["x1"] - truth["x1_exact"], state["x2"][~outliers] - truth["x2_exact"][~outliers]])
    assert error.std() == pytest.approx(0.7, rel=0.05) and abs(error.mean()) < 0.05
    lines = np.column_stack([truth["x1_exact"], np.ones(2000)]) @ truth["F"].T
    distance = np.abs(np.sum(lines[:, :2] * state["x2"], axis=1) + lines[:, 2]) / np.hypot(lines[:, 0], lines[:, 1])
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


# --- rendered ---------------------------------------------------------------------------------------
def test_rendered_truth_is_exact(small_render):
    state, truth = small_render.state, small_render.truth
    assert set(state) == {"images", "K1", "K2"}
    assert state["images"][0].pixels.shape == (120, 160, 3)
    assert truth["depth"].shape == (2, 120, 160)
    assert np.linalg.norm(truth["t"]) == pytest.approx(0.5, rel=1e-9)
    np.testing.assert_allclose(truth["R"] @ truth["R"].T, np.eye(3), atol=1e-12)
    cameras = truth["cameras"]
    R_rel = cameras.R[1] @ cameras.R[0].T
    np.testing.assert_allclose(R_rel, truth["R"], atol=1e-12)
    np.testing.assert_allclose(cameras.t[1] - R_rel @ cameras.t[0], truth["t"], atol=1e-12)
    x1, x2 = truth["x1_exact"], truth["x2_exact"]
    assert len(x1) > 100
    assert np.abs(_algebraic(truth["F"], x1, x2)).max() < 1e-9
    # the depth agrees with the relative pose: lift x1, move, project = x2
    z = truth["depth"][0][x1[:, 1].astype(int), x1[:, 0].astype(int)]
    points = np.column_stack([x1, np.ones(len(x1))]) @ np.linalg.inv(truth["K1"]).T * z[:, None]
    np.testing.assert_allclose(project_points(points, truth["K2"], None, truth["R"], truth["t"]), x2, atol=1e-6)


def test_rendered_zero_baseline_and_errors():
    loaded = rendered(width=64, height=48, supersample=1, baseline=0.0)
    assert np.linalg.norm(loaded.truth["t"]) == 0 and not np.any(loaded.truth["F"])
    assert rotation_angle_deg(loaded.truth["R"], np.eye(3)) > 0.1
    with pytest.raises(InvalidValue, match="at most"):
        rendered(width=64, height=48, baseline=7.0)


def test_rendered_noise_changes_the_images_only():
    a = rendered(width=64, height=48, supersample=1, noise=0.0)
    b = rendered(width=64, height=48, supersample=1, noise=0.05)
    difference = b.state["images"][0].pixels - a.state["images"][0].pixels
    assert 0.03 < difference.std() < 0.06
    np.testing.assert_array_equal(a.truth["depth"], b.truth["depth"])


# --- photos -----------------------------------------------------------------------------------------
def test_read_k_file_known_answer():
    names, K = read_k_file(str(SAMPLES / "essential_mat_data.txt"))
    assert names == ("leuvenA.jpg", "leuvenB.jpg")
    np.testing.assert_allclose(K, LEUVEN_K)


def test_photos_with_a_k_file():
    loaded = photos(path=str(SAMPLES), k_file="essential_mat_data.txt")
    assert loaded.truth == {}
    images = loaded.state["images"]
    assert images.names == ("leuvenA.jpg", "leuvenB.jpg")
    assert (images[0].width, images[0].height) == (751, 563)
    np.testing.assert_allclose(loaded.state["K1"], LEUVEN_K)
    np.testing.assert_allclose(loaded.state["K2"], LEUVEN_K)


def test_photos_shrunk_scale_k():
    loaded = photos(path=str(SAMPLES), k_file="essential_mat_data.txt", max_side=376)
    image = loaded.state["images"][0]
    assert max(image.width, image.height) == 376
    s = image.width / 751
    K = loaded.state["K1"]
    assert K[0, 0] == pytest.approx(LEUVEN_K[0, 0] * s) and K[1, 1] == pytest.approx(LEUVEN_K[1, 1] * s)
    assert K[0, 2] == pytest.approx((LEUVEN_K[0, 2] + 0.5) * s - 0.5)


def test_photos_with_k_options_and_with_a_guess(tmp_path):
    for name in ("leuvenA.jpg", "leuvenB.jpg"):
        shutil.copy(SAMPLES / name, tmp_path / name)
    given = photos(path=str(tmp_path), fx=700.0)
    np.testing.assert_allclose(given.state["K1"], [[700, 0, 375], [0, 700, 281], [0, 0, 1]])
    guessed = photos(path=str(tmp_path))
    np.testing.assert_allclose(guessed.state["K2"], [[1.2 * 751, 0, 375], [0, 1.2 * 751, 281], [0, 0, 1]])
    assert "guessed" in guessed.description


def test_photos_of_different_sizes_without_k_have_no_k(tmp_path):
    shutil.copy(SAMPLES / "leuvenA.jpg", tmp_path / "a.jpg")
    small = cv2.resize(cv2.imread(str(SAMPLES / "leuvenB.jpg")), (400, 300))
    cv2.imwrite(str(tmp_path / "b.png"), small)
    loaded = photos(path=str(tmp_path))
    assert "K1" not in loaded.state and "K2" not in loaded.state
    assert "different sizes" in loaded.description or "differ in size" in loaded.description


def test_photos_errors(tmp_path):
    with pytest.raises(InvalidValue, match="no folder"):
        photos(path=str(tmp_path / "missing"))
    with pytest.raises(InvalidValue, match="two are"):
        photos(path=str(SAMPLES), pattern="left0*.jpg")
    with pytest.raises(InvalidValue, match="pattern"):
        photos(path=str(SAMPLES), pattern="../*.jpg")
    with pytest.raises(InvalidValue, match="k_file"):
        photos(path=str(SAMPLES), k_file="../essential_mat_data.txt")
    (tmp_path / "k.txt").write_text("a.jpg\nb.jpg\n1 0 0\n0 1 0\n")
    with pytest.raises(InvalidValue, match="three rows"):
        photos(path=str(tmp_path), k_file="k.txt")
    (tmp_path / "k.txt").write_text("a.jpg\nb.jpg\n1 0 0\n0 1 0\n0 0 1\n")
    with pytest.raises(InvalidValue, match="not in"):
        photos(path=str(tmp_path), k_file="k.txt")
    (tmp_path / "k.txt").write_text("a.jpg\nb.jpg\n1 0 x\n0 1 0\n0 0 1\n")
    with pytest.raises(InvalidValue, match="numbers"):
        photos(path=str(tmp_path), k_file="k.txt")
    (tmp_path / "a.jpg").write_bytes(b"not an image")
    (tmp_path / "b.jpg").write_bytes(b"not an image")
    with pytest.raises(InvalidValue, match="cannot read"):
        photos(path=str(tmp_path), pattern="*.jpg")


def test_image_values_are_float_rgb(small_render):
    for image in small_render.state["images"].images:
        assert isinstance(image, Image) and image.pixels.dtype == np.float32
        assert 0.0 <= image.pixels.min() and image.pixels.max() <= 1.0
