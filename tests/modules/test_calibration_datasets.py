"""Calibration's datasets: the board, the synthetic generator with exact truth, the folder loader."""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.core import Image, ImageSet, InvalidValue, Mesh, Points2D
from lab.modules.calibration import BACKGROUND, BLACK, WHITE, Checkerboard, folder, synthetic
from lab.geometry.camera import project_points

SAMPLES = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "opencv-samples"
SMALL = dict(num_views=3, width=320, height=240, fx=180.0, fy=178.0, cx=159.0, cy=121.0, seed=5)


@pytest.fixture(scope="module")
def small():
    return synthetic(**SMALL)


def _detect(image: Image, board: Checkerboard) -> np.ndarray:
    gray = image.gray()
    gray8 = np.clip(gray * 255 + 0.5, 0, 255).astype(np.uint8)
    found, xy = cv2.findChessboardCorners(gray8, board.pattern_size)
    assert found
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    return cv2.cornerSubPix(gray, xy, (5, 5), (-1, -1), criteria).reshape(-1, 2)


# --- Checkerboard -----------------------------------------------------------------------------------
def test_object_points_follow_opencv_order():
    board = Checkerboard(9, 6, 0.025)
    points = board.object_points()
    assert points.shape == (54, 3) and points.dtype == np.float64
    np.testing.assert_allclose(points[1], [0.025, 0.0, 0.0])  # along the row first
    np.testing.assert_allclose(points[9], [0.0, 0.025, 0.0])
    np.testing.assert_allclose(points[-1], [8 * 0.025, 5 * 0.025, 0.0])
    assert board.pattern_size == (9, 6) and board.num_corners == 54


@pytest.mark.parametrize("kwargs", [dict(columns=1), dict(rows=0), dict(columns=2.5), dict(square_size=0.0),
                                    dict(square_size=float("nan")), dict(columns=True)])
def test_checkerboard_rejects_bad_sizes(kwargs):
    with pytest.raises(InvalidValue):
        Checkerboard(**kwargs)


def test_labels_known_answers():
    board = Checkerboard(9, 6, 1.0)
    X = np.array([0.5, 1.5, -0.5, 8.5, 9.5, -1.5, 4.0 + 0.5, -3.0])
    Y = np.array([0.5, 0.5, -0.5, 5.5, 6.5, 2.5, 2.0 + 0.5, 0.0])
    expected = [BLACK, WHITE, BLACK, WHITE, WHITE, WHITE, BLACK, BACKGROUND]
    # square (a, b) is black when a + b is even: (-1, -1) black, (8, 5) white (the corner squares of a
    # 9 x 6 board differ, which tells its ends apart); x = 9.5 and x = -1.5 lie in the paper margin
    np.testing.assert_array_equal(board.labels(X, Y), expected)


def test_mesh_has_one_flat_coloured_quad_per_square():
    mesh = Checkerboard(4, 3, 0.1).mesh()
    assert isinstance(mesh, Mesh)
    squares = 5 * 4
    assert mesh.vertices.shape == (4 * squares, 3) and mesh.faces.shape == (2 * squares, 3)
    np.testing.assert_allclose(mesh.vertices[:, 2], 0.0)
    np.testing.assert_allclose(mesh.vertices[:, :2].min(axis=0), [-0.1, -0.1])
    np.testing.assert_allclose(mesh.vertices[:, :2].max(axis=0), [0.4, 0.3])
    assert set(np.round(mesh.vertex_colors[:, 0], 2)) == {0.05, 0.95}


# --- synthetic ----------------------------------------------------------------------------------------
def test_synthetic_state_and_truth_shapes(small):
    images, board = small.state["images"], small.state["board"]
    assert isinstance(images, ImageSet) and len(images) == 3
    assert images.names == ("view 00", "view 01", "view 02")
    assert all(im.pixels.shape == (240, 320) and im.pixels.dtype == np.float32 for im in images.images)
    assert all(im.pixels.min() >= 0.0 and im.pixels.max() <= 1.0 for im in images.images)
    assert board == Checkerboard(9, 6, 0.025)
    truth = small.truth
    assert truth["K"].shape == (3, 3) and truth["dist"].shape == (5,)
    assert truth["rotations"].shape == (3, 3, 3) and truth["translations"].shape == (3, 3)
    corners = truth["corners"]
    assert isinstance(corners, Points2D) and len(corners) == 3 * 54
    np.testing.assert_array_equal(corners.view, np.repeat(np.arange(3), 54))
    np.testing.assert_array_equal(corners.ids, np.tile(np.arange(54), 3))


def test_synthetic_truth_is_consistent(small):
    truth = small.truth
    np.testing.assert_allclose(np.linalg.det(truth["rotations"]), 1.0)
    expected = project_points(Checkerboard().object_points()[None], truth["K"], truth["dist"],
                              truth["rotations"], truth["translations"])
    np.testing.assert_allclose(truth["corners"].xy, expected.reshape(-1, 2))
    assert np.all(truth["translations"][:, 2] > 0)
    xy = truth["corners"].xy
    assert np.all(xy >= 0) and np.all(xy[:, 0] <= 319) and np.all(xy[:, 1] <= 239)  # whole board inside


def test_synthetic_boards_are_tilted_in_different_directions(small):
    normals = small.truth["rotations"][:, :, 2]  # the board's normal in each camera
    tilt = np.degrees(np.arccos(np.abs(normals[:, 2])))
    assert np.all(tilt > 15)  # half the default spread at least: Zhang's method needs tilted boards
    assert np.linalg.matrix_rank(normals, tol=0.05) == 3


def test_synthetic_is_reproducible_and_seeded(small):
    again = synthetic(**SMALL)
    np.testing.assert_array_equal(again.state["images"][0].pixels, small.state["images"][0].pixels)
    other = synthetic(**{**SMALL, "seed": 6, "num_views": 1})
    assert not np.allclose(other.truth["rotations"][0], small.truth["rotations"][0])


def test_synthetic_corners_are_where_the_truth_says(small):
    board = small.state["board"]
    errors = np.concatenate([_detect(im, board) - small.truth["corners"].in_view(v).xy
                             for v, im in enumerate(small.state["images"].images)])
    assert np.sqrt(np.mean(errors**2)) < 0.35  # the default corner noise is 0.2 px per axis
    assert np.abs(errors.mean(axis=0)).max() < 0.05  # and unbiased


def test_corner_noise_sigma_really_moves_the_corners():
    options = dict(num_views=4, seed=2)
    clean = synthetic(noise_px=0.0, image_noise=0.0, **options)
    noisy = synthetic(noise_px=0.5, **options)
    board = clean.state["board"]

    def errors(loaded):
        return np.concatenate([_detect(im, board) - loaded.truth["corners"].in_view(v).xy
                               for v, im in enumerate(loaded.state["images"].images)])

    np.testing.assert_allclose(clean.truth["corners"].xy, noisy.truth["corners"].xy)  # truth keeps exact p_i
    assert np.sqrt(np.mean(errors(clean) ** 2)) < 0.05  # the renderer itself is accurate
    assert 0.42 < errors(noisy).std() < 0.58  # ~ sigma = 0.5 px per axis


def test_synthetic_color_images_are_rgb():
    loaded = synthetic(**{**SMALL, "num_views": 1, "color": True})
    assert loaded.state["images"][0].pixels.shape == (240, 320, 3)


def test_synthetic_rejects_a_principal_point_outside_the_image():
    with pytest.raises(InvalidValue):
        synthetic(**{**SMALL, "cx": 400.0})


def test_synthetic_rejects_a_folding_distortion():
    with pytest.raises(InvalidValue):
        synthetic(**{**SMALL, "num_views": 1, "k1": 1.0, "k2": -1.0})


# --- folder -------------------------------------------------------------------------------------------
def test_folder_reads_photos_sorted_by_name(tmp_path):
    for name in ("left03.jpg", "left01.jpg"):
        shutil.copy(SAMPLES / name, tmp_path / name)
    (tmp_path / "notes.txt").write_text("not an image")
    loaded = folder(path=str(tmp_path), columns=9, rows=6, square_size=0.025)
    images = loaded.state["images"]
    assert images.names == ("left01.jpg", "left03.jpg")
    assert images[0].pixels.shape[:2] == (480, 640) and images[0].pixels.dtype == np.float32
    assert loaded.truth == {}
    assert loaded.state["board"] == Checkerboard(9, 6, 0.025)


def test_folder_pattern_selects_files(tmp_path):
    for name in ("left01.jpg", "leuvenA.jpg"):
        shutil.copy(SAMPLES / name, tmp_path / name)
    assert folder(path=str(tmp_path), pattern="left*").state["images"].names == ("left01.jpg",)


def test_folder_errors_are_clear(tmp_path):
    with pytest.raises(InvalidValue, match="no folder"):
        folder(path=str(tmp_path / "missing"))
    with pytest.raises(InvalidValue, match="no images"):
        folder(path=str(tmp_path))
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(InvalidValue, match=r"broken\.png"):
        folder(path=str(tmp_path))
    with pytest.raises(InvalidValue):
        folder(path=str(tmp_path), pattern="../*")
    with pytest.raises(InvalidValue):
        folder(path=str(tmp_path), columns=1)
