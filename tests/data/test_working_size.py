"""12-megapixel photos (issue 19 item 5): every folder dataset reads 4000 x 3000 photos at a working size,
within a memory budget, with K scaled and the description saying so; ``max_side=0`` reads full resolution.

Photos are generated here (a smooth random picture enlarged to 4000 x 3000, written as JPEG or PNG); the
memory is the peak of Python-visible allocations (tracemalloc: numpy's and OpenCV's arrays; a decode buffer
inside libjpeg is not counted, it is a few rows).
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.core import InvalidValue
from lab.data.files import WORKING_SIDE, read_image_file, read_working_images, working_size
from lab.geometry.camera import scale_intrinsics

WIDTH, HEIGHT = 4000, 3000
#: Peak Python-visible memory of reading three 4000 x 3000 JPEGs at the working size: their float32
#: working pixels (3 x 1600 x 1200 x 3 x 4 bytes = 69 MB) and one reduced decode, not three full photos
#: (3 x 144 MB of float32).
PEAK_THREE_JPEGS_MB = 100


def photo(seed: int, *, gray: bool = False) -> np.ndarray:
    """A 4000 x 3000 uint8 BGR (or grey) picture with detail at every scale SIFT looks at."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(150, 200) if gray else (150, 200, 3), dtype=np.uint8)
    big = cv2.resize(small, (WIDTH, HEIGHT), interpolation=cv2.INTER_CUBIC)
    fine = rng.integers(0, 40, size=big.shape, dtype=np.uint8)
    return cv2.add(big, fine)


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """Three 4000 x 3000 JPEG photos and one PNG, and a grey JPEG, in separate sub-folders."""
    root = tmp_path_factory.mktemp("photos12mp")
    (root / "jpeg").mkdir()
    for i in range(3):
        cv2.imwrite(str(root / "jpeg" / f"photo{i}.jpg"), photo(i), [cv2.IMWRITE_JPEG_QUALITY, 90])
    (root / "png").mkdir()
    cv2.imwrite(str(root / "png" / "photo.png"), photo(7), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    (root / "gray").mkdir()
    cv2.imwrite(str(root / "gray" / "photo.jpg"), photo(8, gray=True))
    return root


def test_working_size_known_answers():
    assert working_size((4000, 3000), 1600) == (1600, 1200)
    assert working_size((3000, 4000), 1600) == (1200, 1600)
    assert working_size((800, 600), 1600) == (800, 600)  # never enlarged
    assert working_size((4000, 3000), 0) == (4000, 3000)
    assert working_size((4001, 3), 1600) == (1600, 1)


def test_scale_intrinsics_keeps_the_image_edge_and_centre():
    K = np.array([[3000.0, 2.0, 1999.5], [0.0, 3100.0, 1499.5], [0.0, 0.0, 1.0]])
    half = scale_intrinsics(K, 0.5)
    np.testing.assert_allclose(half, [[1500.0, 1.0, 999.5], [0.0, 1550.0, 749.5], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(scale_intrinsics(half, 2.0), K)
    assert scale_intrinsics(K, 1.0) is not K


@pytest.mark.parametrize("kind", ["jpeg", "png"])
def test_a_large_photo_is_read_at_the_working_size_as_area_averaging_would(folder, kind):
    file = next((folder / kind).iterdir())
    read = read_working_images([str(file)])
    (image,) = read.images
    assert (image.width, image.height) == (1600, 1200) and image.pixels.dtype == np.float32
    assert read.scales == (0.4,) and read.original_sizes == ((WIDTH, HEIGHT),)
    full = cv2.imread(str(file), cv2.IMREAD_COLOR)
    expected = cv2.resize(full, (1600, 1200), interpolation=cv2.INTER_AREA)[:, :, ::-1] / 255.0
    # PNG: the same area average; JPEG: decoded at half size by libjpeg's DCT scaling first
    tolerance = 1.5 / 255 if kind == "png" else 0.02
    assert np.mean(np.abs(image.pixels - expected)) < tolerance
    assert "1600 x 1200 instead of 4000 x 3000" in read.note and "max_side=0" in read.note


def test_full_resolution_and_small_photos_are_read_as_they_are(folder):
    file = str(folder / "png" / "photo.png")
    full = read_working_images([file], max_side=0)
    assert (full.images[0].width, full.images[0].height) == (WIDTH, HEIGHT) and full.scales == (1.0,)
    assert full.note == ""
    assert read_image_file(file).shape == (HEIGHT, WIDTH, 3)
    with pytest.raises(InvalidValue, match="max_side"):
        read_working_images([file], max_side=-1)


def test_a_grey_jpeg_stays_grey(folder):
    (image,) = read_working_images([str(folder / "gray" / "photo.jpg")]).images
    assert image.pixels.shape == (1200, 1600)


def test_three_12_megapixel_photos_stay_within_the_memory_budget(folder):
    files = sorted(str(f) for f in (folder / "jpeg").iterdir())
    tracemalloc.start()
    try:
        read = read_working_images(files)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(read.images) == 3
    assert peak / 2**20 < PEAK_THREE_JPEGS_MB, f"peak {peak / 2**20:.0f} MB"


# --- every folder dataset ------------------------------------------------------------------------------
def test_epipolar_photos_scale_k_from_the_files_size(folder):
    from lab.modules.epipolar.datasets import photos

    loaded = photos(path=str(folder / "jpeg"), pattern="photo[01].jpg", fx=3200.0)
    images = loaded.state["images"]
    assert all((im.width, im.height) == (1600, 1200) for im in images.images)
    K = np.array([[3200.0, 0.0, 1999.5], [0.0, 3200.0, 1499.5], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(loaded.state["K1"], scale_intrinsics(K, 0.4))
    np.testing.assert_allclose(loaded.state["K1"][:2, 2], [799.5, 599.5])
    assert "working size" in loaded.description
    full = photos(path=str(folder / "jpeg"), pattern="photo[01].jpg", fx=3200.0, max_side=0)
    assert full.state["images"][0].width == WIDTH and "working size" not in full.description
    np.testing.assert_allclose(full.state["K1"], K)


def test_sfm_photos_read_at_the_working_size(folder):
    from lab.modules.sfm.datasets import photos

    loaded = photos(path=str(folder / "jpeg"))
    images, K = loaded.state["images"], loaded.state["K"]
    assert len(images) == 3 and all((im.width, im.height) == (1600, 1200) for im in images.images)
    assert K.shape == (3, 3, 3) and np.allclose(K[:, :2, 2], [799.5, 599.5])
    assert "working size" in loaded.description
    assert WORKING_SIDE == 1600


def test_calibration_folder_reads_at_the_working_size(folder):
    from lab.modules.calibration.datasets import folder as calibration_folder

    loaded = calibration_folder(path=str(folder / "jpeg"))
    assert all((im.width, im.height) == (1600, 1200) for im in loaded.state["images"].images)
    assert "K is estimated for the working size" in loaded.description


def test_texture_image_file_decodes_a_12_megapixel_photo_small(folder):
    from lab.data.textures import image_file

    loaded = image_file(path=str(folder / "jpeg" / "photo0.jpg"), max_size=128)
    assert loaded.state["sample"].pixels.shape == (96, 128, 3)


def test_stereo_folder_reads_a_12_megapixel_pair_at_the_working_size(tmp_path):
    from lab.modules.stereo.datasets import folder as stereo_folder

    left = photo(11)
    right = np.roll(left, -40, axis=1)  # a rectified pair: 40 px of disparity at full size
    cv2.imwrite(str(tmp_path / "left.jpg"), left)
    cv2.imwrite(str(tmp_path / "right.jpg"), right)
    truth = np.full((HEIGHT, WIDTH), 40.0, dtype=np.float32)
    truth[:10] = -1.0  # unknown rows stay unknown
    cv2.imwrite(str(tmp_path / "disp.pfm"), truth)
    (tmp_path / "calib.txt").write_text("cam0=[3000 0 1999.5; 0 3000 1499.5; 0 0 1]\n"
                                        "cam1=[3000 0 1999.5; 0 3000 1499.5; 0 0 1]\ndoffs=0\nbaseline=100\n"
                                        f"width={WIDTH}\nheight={HEIGHT}\n")
    loaded = stereo_folder(path=str(tmp_path))
    left_image = loaded.state["left_raw"]
    assert (left_image.width, left_image.height) == (1600, 1200)
    assert "working size" in loaded.description
    K = loaded.state["calibration"].K_left
    np.testing.assert_allclose(K[:2, 2], [799.5, 599.5])
    np.testing.assert_allclose(K[0, 0], 1200.0)
    disparity = loaded.truth["disparity"]
    assert disparity.shape == (1200, 1600)
    np.testing.assert_allclose(disparity[disparity >= 0], 16.0)  # 40 px at 0.4 of the size
    assert np.all(disparity[:3] == -1.0)
