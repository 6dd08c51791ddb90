"""The chain SfM -> NeRF: an SfM export (COLMAP text) read as a NeRF dataset, held-out cameras aligned."""

import os

import numpy as np
import pytest

from lab.core import InvalidValue
from lab.data.exports import write_reconstruction
from lab.data.reconstruction import SparseModel
from lab.geometry.alignment import Similarity, apply_similarity, similarity_of_cameras
from lab.geometry.camera import project_points
from lab.geometry.rotations import rotvec_to_matrix
from lab.modules.nerf.datasets import _read_split, object_scene, write_nerf_synthetic
from lab.modules.nerf.sfm_dataset import bounds_from_points, sfm_reconstruction

#: The frame SfM recovers: the true world moved by a similarity (SfM knows the scene only up to one).
SFM_FRAME = Similarity(0.4, rotvec_to_matrix(np.array([0.2, -0.5, 1.1])), np.array([0.3, 1.0, -2.0]))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    folder = str(tmp_path_factory.mktemp("reference"))
    return write_nerf_synthetic(folder, object_scene(0), size=32, views=(6, 1, 3))


def _sfm_export(reference: str, folder: str, *, drop: int | None = None) -> str:
    """What SfM would export for the reference's training views: their true cameras and points of the
    object, all moved into :data:`SFM_FRAME`, written by the SfM module's own COLMAP writer."""
    _, train = _read_split(reference, "train", 100, 1)
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.4, 0.4, (40, 3))
    keypoints = [project_points(points, k, None, r, tt)
                 for k, r, tt in zip(train.K, train.R, train.t, strict=True)]
    R, t = similarity_of_cameras(SFM_FRAME, train.R, train.t)
    names = [f"r_{i}.png" for i in range(len(train))]
    views = [v for v in range(len(train)) if v != drop]
    model = SparseModel.from_tracks(
        train.K[views], np.tile([train.width, train.height], (len(views), 1)), R[views], t[views],
        [names[v] for v in views], [keypoints[v] for v in views], apply_similarity(SFM_FRAME, points),
        np.full((40, 3), 128, np.uint8), np.zeros(40),
        [np.column_stack([np.arange(len(views)), np.full(len(views), p)]) for p in range(40)])
    return str(write_reconstruction(folder, model, "colmap"))


def test_held_out_cameras_come_into_the_sfm_frame_by_the_alignment(reference, tmp_path):
    model = _sfm_export(reference, str(tmp_path / "sparse"))
    loaded = sfm_reconstruction(path=model, images=os.path.join(reference, "train"), reference=reference)
    state, truth = loaded.state, loaded.truth
    _, true_test = _read_split(reference, "test", 100, 1)
    R, t = similarity_of_cameras(SFM_FRAME, true_test.R, true_test.t)
    np.testing.assert_allclose(state["test_cameras"].R, R, atol=1e-9)
    np.testing.assert_allclose(state["test_cameras"].t, t, atol=1e-9)
    assert truth["alignment"].scale == pytest.approx(1.0 / SFM_FRAME.scale)
    assert truth["train_center_error"] < 1e-9
    assert truth["test_images"].shape == (3, 32, 32, 3)
    assert state["pixel_supersample"] == 1  # read at full size: one ray through each pixel centre
    assert len(state["images"]) == 6 and state["cameras"].image == "images"
    assert state["images"].names[0] == "r_0.png" and len(state["sfm_points"]) == 40
    bounds = state["bounds"]
    object_center = apply_similarity(SFM_FRAME, np.zeros(3))
    assert np.linalg.norm(bounds.center - object_center) < 0.25 * SFM_FRAME.scale  # 40 points in a 0.8 m box
    half_diagonal = 1.1 * 0.4 * np.sqrt(3.0) * SFM_FRAME.scale
    assert 0.7 * half_diagonal < bounds.radius < 1.3 * half_diagonal
    assert 0 < bounds.near < bounds.far


def test_without_a_reference_every_nth_image_is_held_out_with_its_sfm_pose(reference, tmp_path):
    model = _sfm_export(reference, str(tmp_path / "sparse"))
    loaded = sfm_reconstruction(path=model, images=os.path.join(reference, "train"), test_every=4,
                                downscale=2)
    _, true_train = _read_split(reference, "train", 100, 1)
    R, _ = similarity_of_cameras(SFM_FRAME, true_train.R, true_train.t)
    np.testing.assert_allclose(loaded.state["test_cameras"].R, R[[0, 4]], atol=1e-9)
    assert loaded.state["images"].names == ("r_1.png", "r_2.png", "r_3.png", "r_5.png")
    assert loaded.state["cameras"].width == 16 and loaded.truth["test_images"].shape == (2, 16, 16, 3)
    np.testing.assert_allclose(loaded.state["cameras"].K[0, 0, 0], true_train.K[0, 0, 0] / 2)
    # each pixel is the mean of 2 x 2 photo pixels: held-out renders are area-averaged the same way
    assert loaded.state["pixel_supersample"] == 2


def test_bad_input_is_named(reference, tmp_path):
    model = _sfm_export(reference, str(tmp_path / "sparse"))
    with pytest.raises(InvalidValue, match="is not in"):
        sfm_reconstruction(path=model, images=str(tmp_path))
    with pytest.raises(InvalidValue, match="no images folder"):
        sfm_reconstruction(path=model)
    with pytest.raises(InvalidValue, match=r"transforms_train\.json"):
        sfm_reconstruction(path=model, images=os.path.join(reference, "train"), reference=str(tmp_path))
    with pytest.raises(InvalidValue, match="at least 4 finite"):
        bounds_from_points(np.zeros((2, 3)), np.eye(3)[None], np.array([[0.0, 0.0, 3.0]]))
