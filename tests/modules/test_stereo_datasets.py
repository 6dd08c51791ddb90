"""Stereo datasets (lab.modules.stereo.datasets): the motorcycle pair, synthetic pairs with exact disparity, a
user's folder (every file format)."""

import json

import cv2
import numpy as np
import pytest

from lab.core import Image, InvalidValue, UnknownName
from lab.geometry.rectification import StereoCalibration
from lab.geometry.rotations import rotvec_to_matrix
from lab.modules.stereo import (MOTORCYCLE_DOFFS_PX, folder, motorcycle, read_calibration, read_disparity,
                                synthetic)


# --- the motorcycle --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def full():
    return motorcycle()


def test_motorcycle_pair_and_truth(full):
    left, right, calibration = full.state["left_raw"], full.state["right_raw"], full.state["calibration"]
    assert isinstance(left, Image) and left.pixels.shape == (500, 741, 3)
    assert right.pixels.shape == (500, 741, 3)
    assert isinstance(calibration, StereoCalibration) and calibration.is_rectified()
    assert calibration.baseline == pytest.approx(0.193001)
    assert calibration.K_right[0, 2] - calibration.K_left[0, 2] == pytest.approx(MOTORCYCLE_DOFFS_PX)
    disparity = full.truth["disparity"]
    assert disparity.shape == (500, 741) and np.all(np.isfinite(disparity))
    known = disparity >= 0
    assert 0.9 < known.mean() < 0.95 and np.all(disparity[~known] == -1)
    assert disparity[known].min() > 7 and disparity.max() < 61
    depth = full.truth["depth"]  # Z = f B / (d + doffs)
    y, x = np.argwhere(known)[1000]
    assert depth[y, x] == pytest.approx(994.978 * 0.193001 / (disparity[y, x] + MOTORCYCLE_DOFFS_PX))


def test_motorcycle_truth_matches_the_images(full):
    """Known answer: the right image sampled at x - d reproduces the left image where the truth is known."""
    left, right = full.state["left_raw"].gray(), full.state["right_raw"].gray()
    disparity = full.truth["disparity"]
    ys, xs = np.mgrid[0:500, 0:741].astype(np.float32)
    warped = cv2.remap(right, xs - disparity.astype(np.float32), ys, cv2.INTER_LINEAR)
    known = (disparity >= 0) & (xs - disparity > 1)
    assert np.median(np.abs(left - warped)[known]) < 0.02
    assert np.median(np.abs(left - right)[known]) > 0.03  # without the shift they differ


def test_motorcycle_downsampled(full):
    small = motorcycle(downsample=2)
    left = small.state["left_raw"]
    assert left.pixels.shape == (250, 370, 3)
    np.testing.assert_allclose(left.pixels[10, 20],
                               full.state["left_raw"].pixels[20:22, 40:42].mean(axis=(0, 1)), atol=1e-6)
    disparity, original = small.truth["disparity"], full.truth["disparity"]
    block = original[100:102, 200:202]
    if np.all(block >= 0):
        assert disparity[50, 100] == pytest.approx(block.mean() / 2)
    calibration = small.state["calibration"]
    assert calibration.K_left[0, 0] == pytest.approx(994.978 / 2)
    assert calibration.K_left[0, 2] == pytest.approx((311.193 + 0.5) / 2 - 0.5)


# --- synthetic pairs --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rectified_pair():
    return synthetic(width=160, height=120, baseline=0.1)


def test_synthetic_rectified_pair_has_exact_disparity(rectified_pair):
    calibration = rectified_pair.state["calibration"]
    assert calibration.is_rectified()
    disparity, depth = rectified_pair.truth["disparity"], rectified_pair.truth["depth"]
    known = disparity >= 0
    f = calibration.K_left[0, 0]
    np.testing.assert_allclose(disparity[known], f * 0.1 / depth[known])
    # the point seen at left pixel (x, y) projects to (x - d, y) in the right camera
    y, x = 60, 90
    point = depth[y, x] * np.linalg.inv(calibration.K_left) @ np.array([x, y, 1.0])
    projected = calibration.K_right @ (calibration.R @ point + calibration.T)
    np.testing.assert_allclose(projected[:2] / projected[2], [x - disparity[y, x], y], atol=1e-9)


def test_synthetic_rectified_images_agree_through_the_disparity(rectified_pair):
    left, right = rectified_pair.state["left_raw"].pixels, rectified_pair.state["right_raw"].pixels
    disparity = rectified_pair.truth["disparity"].astype(np.float32)
    ys, xs = np.mgrid[0:120, 0:160].astype(np.float32)
    warped = cv2.remap(right, xs - disparity, ys, cv2.INTER_LINEAR)
    inside = (disparity >= 0) & (xs - disparity > 1)
    assert np.median(np.abs(left - warped)[inside]) < 0.03


def test_synthetic_unrectified_pair():
    loaded = synthetic(rectified=False, width=96, height=72, verge_deg=5.0, k1=-0.1, noise=0.01, seed=1)
    calibration = loaded.state["calibration"]
    assert not calibration.is_rectified()
    assert np.allclose(calibration.dist_left, [-0.1, 0, 0, 0, 0])
    assert loaded.truth["points"].shape == (500, 3) and np.all(loaded.truth["points"][:, 2] > 0)
    assert loaded.truth["disparity"].shape == (72, 96)
    assert "verged 5 deg" in loaded.description


def test_synthetic_options_are_checked():
    with pytest.raises(UnknownName, match="moon"):
        synthetic(scene="moon", width=64, height=48)
    with pytest.raises(InvalidValue, match="width"):
        synthetic(width=1, height=48)


# --- a user's folder --------------------------------------------------------------------------------------
def _write_pair(path, *, width=64, height=48, names=("left.png", "right.png")):
    rng = np.random.default_rng(0)
    left = (rng.random((height, width, 3)) * 255).astype(np.uint8)
    right = np.roll(left, -3, axis=1)
    cv2.imwrite(str(path / names[0]), left)
    cv2.imwrite(str(path / names[1]), right)
    return left


def _write_opencv_yaml(path, values):
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in values.items():
        storage.write(key, np.asarray(value, dtype=np.float64) if not np.isscalar(value) else float(value))
    storage.release()


K = np.array([[80.0, 0.0, 31.5], [0.0, 80.0, 23.5], [0.0, 0.0, 1.0]])


def test_folder_rectified_pair_with_json_calibration_and_png_truth(tmp_path):
    _write_pair(tmp_path)
    (tmp_path / "calib.json").write_text(json.dumps({"K": K.tolist(), "baseline": 0.12, "doffs": 2.0}))
    truth = np.full((48, 64), 3, np.uint16)
    truth[0, 0] = 0  # unknown
    cv2.imwrite(str(tmp_path / "disp.png"), truth)
    loaded = folder(path=str(tmp_path))
    calibration = loaded.state["calibration"]
    assert calibration.is_rectified() and calibration.baseline == pytest.approx(0.12)
    assert calibration.K_right[0, 2] == pytest.approx(33.5)
    assert loaded.state["left_raw"].pixels.shape == (48, 64, 3)
    assert loaded.truth["disparity"][0, 0] == -1 and loaded.truth["disparity"][5, 5] == 3.0
    assert "true disparity" in loaded.description
    small = folder(path=str(tmp_path), downsample=2)
    assert small.state["left_raw"].pixels.shape == (24, 32, 3)
    assert small.state["right_raw"].pixels.shape == (24, 32, 3)
    assert small.state["calibration"].K_left[0, 0] == 40.0 and small.state["calibration"].K_left[0, 2] == 15.5
    assert small.truth["disparity"][0, 0] == 1.5 and small.truth["disparity"][5, 5] == 1.5
    with pytest.raises(InvalidValue, match="too small"):
        folder(path=str(tmp_path), downsample=30)


def test_folder_unrectified_pair_with_opencv_yaml(tmp_path):
    _write_pair(tmp_path, names=("left.jpg", "right.jpg"))
    R = rotvec_to_matrix(np.array([0.01, -0.03, 0.0]))
    _write_opencv_yaml(tmp_path / "calib.yml", {"M1": K, "D1": [-0.05, 0.01, 0, 0, 0], "M2": K,
                                                "D2": [-0.04, 0.0, 0, 0, 0], "R": R,
                                                "T": [[-0.1], [0.002], [0.0]]})
    calibration = folder(path=str(tmp_path)).state["calibration"]
    assert not calibration.is_rectified()
    np.testing.assert_allclose(calibration.R, R, atol=1e-12)
    np.testing.assert_allclose(calibration.T, [-0.1, 0.002, 0.0])
    np.testing.assert_allclose(calibration.dist_left, [-0.05, 0.01, 0, 0, 0])


def test_folder_middlebury_layout(tmp_path):
    _write_pair(tmp_path, names=("im0.png", "im1.png"))
    (tmp_path / "calib.txt").write_text("cam0=[80 0 31.5; 0 80 23.5; 0 0 1]\n"
                                        "cam1=[80 0 35.5; 0 80 23.5; 0 0 1]\n"
                                        "doffs=4\nbaseline=120.0\nwidth=64\nheight=48\nndisp=16\n")
    truth = np.full((48, 64), 3.5, np.float32)
    truth[1, 2] = np.inf
    cv2.imwrite(str(tmp_path / "disp0.pfm"), truth)
    loaded = folder(path=str(tmp_path))
    calibration = loaded.state["calibration"]
    assert calibration.baseline == pytest.approx(0.12)  # millimetres in calib.txt
    assert calibration.K_right[0, 2] - calibration.K_left[0, 2] == pytest.approx(4.0)
    assert loaded.truth["disparity"][1, 2] == -1 and loaded.truth["disparity"][0, 0] == pytest.approx(3.5)


def test_folder_without_calibration_is_taken_as_rectified(tmp_path):
    _write_pair(tmp_path)
    loaded = folder(path=str(tmp_path))
    calibration = loaded.state["calibration"]
    assert calibration.is_rectified() and calibration.K_left[0, 0] == 64.0 and calibration.baseline == 1.0
    assert loaded.truth == {}


def test_read_disparity_formats(tmp_path):
    values = np.array([[0, 7], [300, 12]], np.uint16)
    cv2.imwrite(str(tmp_path / "d.png"), values)
    np.testing.assert_array_equal(read_disparity(str(tmp_path / "d.png")), [[-1, 7], [300, 12]])
    floats = np.array([[np.inf, 2.5], [-1.0, 4.0]], np.float32)
    cv2.imwrite(str(tmp_path / "d.pfm"), floats)
    np.testing.assert_array_equal(read_disparity(str(tmp_path / "d.pfm")), [[-1, 2.5], [-1, 4.0]])


def test_folder_errors(tmp_path):
    with pytest.raises(InvalidValue, match="no folder"):
        folder(path=str(tmp_path / "missing"))
    with pytest.raises(InvalidValue, match="left"):
        folder(path=str(tmp_path))
    _write_pair(tmp_path)
    cv2.imwrite(str(tmp_path / "right.png"), np.zeros((40, 64, 3), np.uint8))
    with pytest.raises(InvalidValue, match="differ in size"):
        folder(path=str(tmp_path))
    _write_pair(tmp_path)
    (tmp_path / "calib.json").write_text(json.dumps({"focal": 3}))
    with pytest.raises(InvalidValue, match="needs either K and baseline"):
        folder(path=str(tmp_path))
    (tmp_path / "calib.json").write_text("{not json")
    with pytest.raises(InvalidValue, match="cannot be read"):
        folder(path=str(tmp_path))
    (tmp_path / "calib.json").write_text(json.dumps({"K": K.tolist(), "baseline": 0.0}))
    with pytest.raises(InvalidValue, match="baseline"):
        folder(path=str(tmp_path))
    (tmp_path / "calib.json").write_text(json.dumps({"K1": K.tolist(), "R": np.eye(3).tolist(),
                                                     "T": [0, 0, 0]}))
    with pytest.raises(InvalidValue, match="K1/M1 and K2/M2"):
        folder(path=str(tmp_path))
    (tmp_path / "calib.json").write_text(json.dumps({"K1": K.tolist(), "K2": K.tolist(),
                                                     "R": np.eye(3).tolist(), "T": [0, 0, 0]}))
    with pytest.raises(InvalidValue, match="baseline is zero"):
        folder(path=str(tmp_path))


def test_folder_refuses_truth_for_an_unrectified_pair(tmp_path):
    _write_pair(tmp_path)
    (tmp_path / "calib.json").write_text(json.dumps({"K1": K.tolist(), "K2": K.tolist(),
                                                     "D1": [-0.1, 0, 0, 0, 0], "R": np.eye(3).tolist(),
                                                     "T": [-0.1, 0, 0]}))
    cv2.imwrite(str(tmp_path / "disp.png"), np.full((48, 64), 3, np.uint8))
    with pytest.raises(InvalidValue, match="rectified already"):
        folder(path=str(tmp_path))


def test_read_calibration_names_the_file(tmp_path):
    path = tmp_path / "calib.yml"
    path.write_text("%YAML:1.0\n---\nK: [1, 2]\nbaseline: 0.1\n")
    with pytest.raises(InvalidValue, match=r"calib\.yml"):
        read_calibration(str(path))
