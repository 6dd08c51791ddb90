"""Export writers: values through the codecs to files, and OpenCV's calibration YAML both ways."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.core import Image, ImageSet, InvalidValue, PointCloud
from lab.data.exports import read_opencv_calibration, write_opencv_calibration, write_value

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "opencv-samples"
K = np.array([[812.5, 0.25, 319.5], [0.0, 815.0, 241.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.21, 0.08, 0.0012, -0.0007, -0.015])


def test_opencv_calibration_round_trip(tmp_path):
    path = write_opencv_calibration(tmp_path / "a" / "camera.yml", K, DIST, image_width=640, image_height=480,
                                    avg_reprojection_error=0.31, per_view_reprojection_errors=[0.3, 0.32],
                                    board_width=9, board_height=6, square_size=0.025)
    back = read_opencv_calibration(path)
    np.testing.assert_array_equal(back.K, K)  # doubles are written with 17 digits: exact
    np.testing.assert_array_equal(back.dist, DIST)
    assert (back.image_width, back.image_height) == (640, 480)
    assert back.avg_reprojection_error == pytest.approx(0.31)


def test_opencv_calibration_nodes_as_opencv_sample_names_them(tmp_path):
    path = write_opencv_calibration(tmp_path / "camera.txt", K, DIST, image_width=640, image_height=480,
                                    per_view_reprojection_errors=np.array([0.1, 0.2, 0.3]),
                                    board_width=9, board_height=6, square_size=0.03)
    text = path.read_text()
    assert text.startswith("%YAML")  # YAML whatever the suffix
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        assert storage.getNode("camera_matrix").mat().shape == (3, 3)
        assert storage.getNode("distortion_coefficients").mat().shape == (5, 1)
        assert storage.getNode("nframes").real() == 3
        assert storage.getNode("board_width").real() == 9 and storage.getNode("board_height").real() == 6
        assert storage.getNode("square_size").real() == pytest.approx(0.03)
        assert storage.getNode("per_view_reprojection_errors").mat().ravel().tolist() == [0.1, 0.2, 0.3]
        assert storage.getNode("avg_reprojection_error").empty()  # not given: not written
    finally:
        storage.release()


def test_extrinsic_parameters_are_rodrigues_and_translation(tmp_path):
    angle = 0.3
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    path = write_opencv_calibration(tmp_path / "c.yaml", K, DIST, image_width=64, image_height=48,
                                    rotations=np.stack([np.eye(3), R]),
                                    translations=[[0, 0, 1], [0.1, 0.2, 2]])
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        extrinsics = storage.getNode("extrinsic_parameters").mat()
        assert storage.getNode("nframes").real() == 2
    finally:
        storage.release()
    np.testing.assert_allclose(extrinsics, [[0, 0, 0, 0, 0, 1], [0, 0, angle, 0.1, 0.2, 2]], atol=1e-12)


def test_reads_opencv_own_calibration_file():
    """OpenCV's calibration of its left*.jpg samples, as its own tool wrote it (../shared/data)."""
    calibration = read_opencv_calibration(SHARED / "left_intrinsics.yml")
    assert calibration.K[0, 0] == pytest.approx(535.91573396163199)
    assert calibration.K[1, 2] == pytest.approx(235.57082909788173)
    assert calibration.dist.shape == (5,) and calibration.dist[0] == pytest.approx(-0.26637260909660682)
    assert (calibration.image_width, calibration.image_height) == (640, 480)
    assert calibration.avg_reprojection_error == pytest.approx(0.39259098975581364)


@pytest.mark.parametrize(("K", "dist", "size", "field"), [
    (np.eye(2), DIST, (640, 480), "K"),
    (np.full((3, 3), np.nan), DIST, (640, 480), "K"),
    (K, np.zeros(3), (640, 480), "dist"),
    (K, DIST, (0, 480), "image_size"),
])
def test_opencv_calibration_refuses_bad_values(tmp_path, K, dist, size, field):
    with pytest.raises(InvalidValue) as caught:
        write_opencv_calibration(tmp_path / "c.yaml", K, dist, image_width=size[0], image_height=size[1])
    assert caught.value.field == field
    assert not (tmp_path / "c.yaml").exists()


def test_read_opencv_calibration_errors(tmp_path):
    with pytest.raises(InvalidValue, match="no such file"):
        read_opencv_calibration(tmp_path / "missing.yaml")
    other = tmp_path / "other.yaml"
    storage = cv2.FileStorage(str(other), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    storage.write("something", 1)
    storage.release()
    with pytest.raises(InvalidValue, match="no camera_matrix"):
        read_opencv_calibration(other)


def test_write_value_formats(tmp_path):
    rng = np.random.default_rng(0)
    images = ImageSet((Image(rng.random((4, 5, 3), dtype=np.float32), "a"),
                       Image(rng.random((4, 5, 3), dtype=np.float32), "b")))
    cloud = PointCloud(rng.random((7, 3)))

    written = write_value(tmp_path / "c.json", cloud, "json", name="cloud")
    assert json.loads(written.read_text())["type"] == "PointCloud"
    np.testing.assert_array_equal(np.load(write_value(tmp_path / "c.npy", cloud, "npy", name="cloud")),
                                  cloud.xyz)
    png = cv2.imread(str(write_value(tmp_path / "deep" / "b.png", images, "png", name="images", index=1)))
    np.testing.assert_array_equal(png[:, :, ::-1],
                                  np.clip(images[1].pixels * 255 + 0.5, 0, 255).astype(np.uint8))
    assert write_value(tmp_path / "c.ply", cloud, "ply", name="cloud").read_bytes().startswith(b"ply")


def test_write_value_errors(tmp_path):
    with pytest.raises(InvalidValue, match="unknown format"):
        write_value(tmp_path / "x", np.zeros(3), "tiff", name="x")
    with pytest.raises(InvalidValue, match="not a point cloud"):
        write_value(tmp_path / "x.ply", Image(np.zeros((2, 2), np.float32)), "ply", name="x")
    with pytest.raises(InvalidValue, match="index"):
        write_value(tmp_path / "x.png", ImageSet((Image(np.zeros((2, 2), np.float32)),)), "png", name="x",
                    index=3)
    assert list(tmp_path.iterdir()) == []
