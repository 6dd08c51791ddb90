"""The epipolar module's datasets (lab.modules.epipolar.datasets).

The rendered pair with exact truth, a user's two photos and their K file; the synthetic correspondences
(lab.data.two_view) are tested in tests/data/test_two_view.py.
"""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.core import Image, InvalidValue
from lab.geometry.camera import project_points
from lab.geometry.rotations import rotation_angle_deg
from lab.modules.epipolar import PIPELINE, correspondences, photos, read_k_file, rendered

SAMPLES = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "opencv-samples"
LEUVEN_K = np.array([[651.4462353114224, 0.0, 376.27522319223914],
                     [0.0, 653.7348054191838, 280.1106539526218], [0.0, 0.0, 1.0]])


def _algebraic(F, x1, x2):
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    return np.sum(h2 * (h1 @ F.T), axis=1)


@pytest.fixture(scope="module")
def small_render():
    return rendered(width=160, height=120, supersample=1, seed=1)


def test_the_pipeline_seeds_from_these_datasets():
    assert [d.name for d in PIPELINE.datasets] == ["rendered", "correspondences", "photos"]
    assert [d.loader for d in PIPELINE.datasets] == [rendered, correspondences, photos]


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
    projected = project_points(points, truth["K2"], None, truth["R"], truth["t"])
    np.testing.assert_allclose(projected, x2, atol=1e-6)


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
        assert image.pixels.min() >= 0.0 and image.pixels.max() <= 1.0
