"""lab.modules.sfm.datasets: rendered multi-view scenes with exact truth, a folder of photos, the course's
match files."""

import cv2
import numpy as np
import pytest

from lab.core import ImageSet, Image, InvalidControl, InvalidValue
from lab.modules.sfm import (FOCAL_GUESS_FACTOR, PIPELINE, camera_path, check_intrinsics, exif_focal_px,
                             match_files, photos, read_k_matrix, rendered, scene_extent)

SMALL = dict(num_views=3, width=96, height=72, supersample=1, noise=0.0)


@pytest.fixture(scope="module")
def small():
    return rendered(**SMALL)


# --- rendered ----------------------------------------------------------------------------------------
def test_rendered_smoke_and_shapes(small):
    images, K = small.state["images"], small.state["K"]
    assert isinstance(images, ImageSet) and len(images) == 3
    assert images[0].pixels.shape == (72, 96, 3)
    assert K.shape == (3, 3, 3)
    truth = small.truth
    assert truth["R"].shape == (3, 3, 3) and truth["t"].shape == (3, 3) and truth["depth"].shape == (3, 72,
                                                                                                     96)
    assert set(small.state) == {"images", "K"}  # truth is never in the state
    assert truth["scene_size"] > 0


def test_rendered_known_answer_depth_reprojects_between_views(small):
    """Pixels of view 0 lifted by their true depth and projected into view 1 land where view 1 sees that depth
    (all but the few hidden in view 1)."""
    truth = small.truth
    K, R, t, depth = truth["K"], truth["R"], truth["t"], truth["depth"]
    v, u = np.mgrid[4:68:4, 4:92:4]
    z = depth[0, v.ravel(), u.ravel()]
    rays = np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)]) @ np.linalg.inv(K[0]).T
    X = (rays * z[:, None] - t[0]) @ R[0]
    x1 = (X @ R[1].T + t[1]) @ K[1].T
    uv = x1[:, :2] / x1[:, 2:]
    inside = (uv[:, 0] > 0) & (uv[:, 0] < 95) & (uv[:, 1] > 0) & (uv[:, 1] < 71) & np.isfinite(z)
    seen = depth[1, np.round(uv[inside, 1]).astype(int), np.round(uv[inside, 0]).astype(int)]
    agree = np.abs(seen - x1[inside, 2]) < 0.03 * x1[inside, 2]
    assert inside.sum() > 30 and agree.mean() > 0.6  # wrong poses agree nowhere near this


def test_rendered_orbit_and_forward_paths():
    _, orbit = camera_path("room", "orbit", num_views=5, arc_deg=90.0)
    _, forward = camera_path("room", "forward", num_views=5, step=0.3, turn_deg=0.0)
    steps = np.linalg.norm(np.diff(forward.centers, axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.3, atol=1e-9)
    radii = np.linalg.norm((orbit.centers - np.array([0.0, 0.0, 0.6]))[:, :2], axis=1)
    np.testing.assert_allclose(radii, radii[0], atol=1e-9)


def test_rendered_is_deterministic_per_seed():
    a, b = rendered(**SMALL, seed=3), rendered(**SMALL, seed=3)
    np.testing.assert_array_equal(a.state["images"][1].pixels, b.state["images"][1].pixels)


def test_rendered_options_are_checked_through_the_pipeline():
    spec = PIPELINE.dataset("rendered")
    with pytest.raises(InvalidControl, match="num_views"):
        spec.load({"num_views": 1})
    with pytest.raises(InvalidControl, match="path"):
        spec.load({"path": "spiral"})


def test_scene_extent_known_answer():
    assert scene_extent(np.array([[0.0, 0, 0], [3, 4, 0], [1, 1, 0]])) == pytest.approx(5.0)
    assert scene_extent(np.zeros((1, 3))) == 0.0


# --- K checks ---------------------------------------------------------------------------------------
def test_check_intrinsics_shares_one_K_and_names_a_misfit():
    images = ImageSet((Image(np.zeros((48, 64, 3))), Image(np.zeros((48, 64, 3)), name="b.png")))
    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    assert check_intrinsics(K, images).shape == (2, 3, 3)
    at_double_size = np.array([[120.0, 0, 63.5], [0, 120.0, 47.5], [0, 0, 1]])
    with pytest.raises(InvalidValue, match=r"does not fit the 64x48 image"):
        check_intrinsics(at_double_size, images)
    with pytest.raises(InvalidValue, match="one camera matrix per image"):
        check_intrinsics(np.stack([K] * 3), images)
    with pytest.raises(InvalidValue, match="positive focal"):
        check_intrinsics(np.diag([-1.0, 1.0, 1.0]), images)


# --- a folder of photos -------------------------------------------------------------------------------
def _write_photos(folder, count=3, size=(80, 60)):
    rng = np.random.default_rng(0)
    for i in range(count):
        cv2.imwrite(str(folder / f"p{i}.png"), rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))


def test_photos_with_fx_and_with_k_file(tmp_path):
    _write_photos(tmp_path)
    loaded = photos(path=str(tmp_path), fx=70.0)
    np.testing.assert_allclose(loaded.state["K"][0], [[70, 0, 39.5], [0, 70, 29.5], [0, 0, 1]])
    assert loaded.truth == {}
    (tmp_path / "K.txt").write_text("# K\n71 0 40\n0 72 30\n0 0 1\n")
    loaded = photos(path=str(tmp_path), k_file="K.txt")
    np.testing.assert_allclose(loaded.state["K"][2], [[71, 0, 40], [0, 72, 30], [0, 0, 1]])
    assert "K from K.txt" in loaded.description


def test_photos_guess_is_reported_as_a_guess(tmp_path):
    _write_photos(tmp_path)
    loaded = photos(path=str(tmp_path))
    assert "GUESSED" in loaded.description
    assert loaded.state["K"][0, 0, 0] == pytest.approx(FOCAL_GUESS_FACTOR * 80)


def test_photos_focal_from_exif(tmp_path):
    from PIL import Image as PILImage

    _write_photos(tmp_path, count=2)
    photo = PILImage.fromarray(np.full((60, 80, 3), 128, dtype=np.uint8))
    exif = PILImage.Exif()
    exif.get_ifd(0x8769)[41989] = 28  # FocalLengthIn35mmFilm
    photo.save(tmp_path / "p2.jpg", exif=exif)
    expected = 28 * np.hypot(80, 60) / np.hypot(36, 24)
    assert exif_focal_px(str(tmp_path / "p2.jpg"), 80, 60) == pytest.approx(expected)
    assert exif_focal_px(str(tmp_path / "p0.png"), 80, 60) is None
    loaded = photos(path=str(tmp_path))
    assert loaded.state["K"][2, 0, 0] == pytest.approx(expected)
    assert "EXIF 35 mm equivalent for 1 of 3" in loaded.description


def test_photos_errors(tmp_path):
    _write_photos(tmp_path, count=1)
    with pytest.raises(InvalidValue, match="at least two"):
        photos(path=str(tmp_path))
    with pytest.raises(InvalidValue, match="no folder"):
        photos(path=str(tmp_path / "missing"))
    _write_photos(tmp_path, count=2)
    (tmp_path / "bad.txt").write_text("fx fy\n1 2\n")
    with pytest.raises(InvalidValue, match="three rows of K"):
        photos(path=str(tmp_path), k_file="bad.txt")
    (tmp_path / "wrong.txt").write_text("300 0 160\n0 300 120\n0 0 1\n")  # calibrated at 320x240
    with pytest.raises(InvalidValue, match="does not fit"):
        photos(path=str(tmp_path), k_file="wrong.txt")


def test_read_k_matrix_takes_the_last_three_rows(tmp_path):
    (tmp_path / "k.txt").write_text("a.png\nb.png\n1 0 2\n0 3 4\n0 0 1\n")
    np.testing.assert_array_equal(read_k_matrix(str(tmp_path / "k.txt")), [[1, 0, 2], [0, 3, 4], [0, 0, 1]])


# --- the course's match files -------------------------------------------------------------------------
def test_match_files_give_keypoints_and_matches(tmp_path):
    _write_photos(tmp_path, count=3)
    (tmp_path / "matching1.txt").write_text("nFeatures: 2\n3 10 20 30 10.5 20.25 2 11.0 21.0 3 12.0 22.0\n"
                                            "2 40 50 60 30.0 5.0 3 31.0 5.5\n")
    (tmp_path / "matching2.txt").write_text("nFeatures: 1\n2 70 80 90 40.0 6.0 3 40.5 6.5\n")
    loaded = match_files(path=str(tmp_path), fx=70.0)
    keypoints, matches = loaded.state["keypoints"], loaded.state["matches"]
    assert matches.shape[1] == 4 and matches.dtype == np.int64
    np.testing.assert_array_equal(np.bincount(keypoints.view), [2, 2, 3])
    for a, b, ka, kb in matches:  # every match joins keypoints of its two images
        assert keypoints.view[ka] == a and keypoints.view[kb] == b and a < b
    row = matches[(matches[:, 0] == 0) & (matches[:, 1] == 2)]
    assert sorted(map(tuple, keypoints.xy[row[:, 3]].tolist())) == [(12.0, 22.0), (31.0, 5.5)]
    np.testing.assert_allclose(keypoints.colors[0], np.array([10, 20, 30]) / 255)


def test_match_files_malformed_line_is_named(tmp_path):
    _write_photos(tmp_path, count=2)
    (tmp_path / "matching1.txt").write_text("nFeatures: 1\n2 10 20 30 10.5\n")
    with pytest.raises(InvalidValue, match="line 2"):
        match_files(path=str(tmp_path), fx=70.0)
