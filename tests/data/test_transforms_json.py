"""lab.data.transforms_json: nerfstudio / instant-ngp transforms.json out and in (OpenGL camera-to-world)."""

import dataclasses
import json
import math

import numpy as np
import pytest
import trimesh

from lab.core import InvalidValue
from lab.data.reconstruction import SparseModel
from lab.data.transforms_json import camera_to_world_opengl, read_transforms_json, write_transforms_json
from lab.geometry.rotations import look_at


def _reconstruction(views: int = 5, shared: bool = True, seed: int = 0) -> SparseModel:
    rng = np.random.default_rng(seed)
    angles = np.linspace(0.0, 2.0, views)
    eyes = np.stack([4 * np.sin(angles), rng.uniform(-1, 1, views), -4 * np.cos(angles)], axis=1)
    R, t = look_at(eyes, np.zeros_like(eyes))
    K = np.array([[[600.0 + (0 if shared else 7 * i), 0.0, 319.5], [0.0, 601.0, 239.5], [0.0, 0.0, 1.0]]
                  for i in range(views)])
    xyz = rng.uniform(-1, 1, (20, 3))
    return SparseModel.from_tracks(K=K, sizes=np.tile([640, 480], (views, 1)), R=R, t=t,
                                   names=tuple(f"frame_{i:03d}.png" for i in range(views)),
                                   keypoints=tuple(np.zeros((0, 2)) for _ in range(views)), points=xyz,
                                   colors=rng.integers(0, 256, (20, 3)), errors=np.zeros(20),
                                   tracks=((),) * 20)


def test_write_smoke_and_layout(tmp_path):
    path = write_transforms_json(tmp_path / "scene" / "transforms.json", _reconstruction())
    data = json.loads(path.read_text())
    assert data["camera_model"] == "OPENCV"
    assert (data["w"], data["h"], data["fl_x"], data["fl_y"]) == (640, 480, 600.0, 601.0)
    assert (data["cx"], data["cy"]) == (320.0, 240.0)  # + 0.5: pixel centres at (0.5, 0.5)
    assert data["camera_angle_x"] == pytest.approx(2 * math.atan(320 / 600))
    assert len(data["frames"]) == 5
    assert data["frames"][0]["file_path"] == "images/frame_000.png"
    assert np.array(data["frames"][0]["transform_matrix"]).shape == (4, 4)


def test_identity_pose_known_answer():
    np.testing.assert_array_equal(camera_to_world_opengl(np.eye(3), np.zeros(3)),
                                  np.diag([1.0, -1.0, -1.0, 1.0]))


def test_transform_matrix_is_opengl_camera_to_world():
    """Its translation is the camera centre and the camera looks down its -z axis, y up."""
    rec = _reconstruction()
    c2w = camera_to_world_opengl(rec.R, rec.t)
    np.testing.assert_allclose(c2w[:, :3, 3], rec.centers, atol=1e-12)
    target_in_camera = np.einsum("nji,nj->ni", c2w[:, :3, :3], -c2w[:, :3, 3])  # the origin, looked at
    assert np.all(target_in_camera[:, 2] < 0)
    np.testing.assert_allclose(target_in_camera[:, :2], 0.0, atol=1e-12)


@pytest.mark.parametrize("shared", [True, False])
def test_round_trip(tmp_path, shared):
    rec = _reconstruction(shared=shared)
    path = write_transforms_json(tmp_path / "transforms.json", rec, image_folder="rgb")
    data = json.loads(path.read_text())
    assert ("fl_x" in data) == shared and ("fl_x" in data["frames"][0]) != shared
    K, sizes, R, t, names = read_transforms_json(path)
    np.testing.assert_allclose(K, rec.K, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sizes, rec.sizes)
    np.testing.assert_allclose(R, rec.R, atol=1e-14)
    np.testing.assert_allclose(t, rec.t, atol=1e-12)
    assert names == tuple(f"rgb/{name}" for name in rec.names)


def test_only_registered_views_are_written(tmp_path):
    rec = _reconstruction()
    fields = {f.name: getattr(rec, f.name) for f in dataclasses.fields(SparseModel)}
    part = SparseModel(**{**fields, "registered": np.array([True, False, True, True, False])})
    _, _, R, t, names = read_transforms_json(write_transforms_json(tmp_path / "t.json", part))
    assert names == ("images/frame_000.png", "images/frame_002.png", "images/frame_003.png")
    np.testing.assert_allclose(R, rec.R[[0, 2, 3]], atol=1e-14)
    np.testing.assert_allclose(t, rec.t[[0, 2, 3]], atol=1e-12)


def test_read_instant_ngp_variant(tmp_path):
    """camera_angle_x only, no principal point (image centre), 3 x 4 matrices."""
    rec = _reconstruction(views=2)
    c2w = camera_to_world_opengl(rec.R, rec.t)
    angle = 2 * math.atan(320 / 500)
    data = {"camera_angle_x": angle, "w": 640, "h": 480,
            "frames": [{"file_path": f"./images/{i}",
                        "transform_matrix": c2w[i][:3].tolist()} for i in range(2)]}
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    K, _, R, _, names = read_transforms_json(tmp_path / "transforms.json")
    np.testing.assert_allclose(K[0], [[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]], atol=1e-9)
    np.testing.assert_allclose(R, rec.R, atol=1e-12)
    assert names == ("./images/0", "./images/1")


def test_points_ply_is_written_and_referenced(tmp_path):
    rec = _reconstruction()
    path = write_transforms_json(tmp_path / "transforms.json", rec, points_ply="sparse_pc.ply")
    assert json.loads(path.read_text())["ply_file_path"] == "sparse_pc.ply"
    cloud = trimesh.load(tmp_path / "sparse_pc.ply")
    np.testing.assert_allclose(np.asarray(cloud.vertices), rec.points, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(cloud.colors)[:, :3], rec.colors)


def test_write_rejects_skew(tmp_path):
    rec = _reconstruction(views=2)
    K = rec.K.copy()
    K[:, 0, 1] = 1.0
    skewed = SparseModel.from_tracks(K, rec.sizes, rec.R, rec.t, rec.names, rec.image_keypoints, rec.points,
                                     rec.colors, rec.errors, rec.tracks)
    with pytest.raises(InvalidValue, match="skew"):
        write_transforms_json(tmp_path / "t.json", skewed)


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(k1=0.1), "distortion"),
    (lambda d: d.pop("w"), "'w' is missing"),
    (lambda d: d.update(camera_model="OPENCV_FISHEYE"), "pinhole"),
    (lambda d: d["frames"][1].update(transform_matrix=[[1, 2], [3, 4]]), r"frames\[1\]"),
    (lambda d: d["frames"][0].update(transform_matrix=(2 * np.eye(4)).tolist()), "not a rotation"),
    (lambda d: d.update(frames=[]), "no 'frames'"),
    (lambda d: [d.pop(k) for k in ("fl_x", "camera_angle_x")], "no focal length"),
])
def test_read_rejects_malformed_files(tmp_path, change, message):
    path = write_transforms_json(tmp_path / "transforms.json", _reconstruction(views=3))
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
    with pytest.raises(InvalidValue, match=message):
        read_transforms_json(path)


def test_read_rejects_missing_and_non_json_files(tmp_path):
    with pytest.raises(InvalidValue, match="no such file"):
        read_transforms_json(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InvalidValue, match="not JSON"):
        read_transforms_json(tmp_path / "bad.json")


def test_export_registry_writes_transforms_json(tmp_path):
    from lab.data.exports import RECONSTRUCTION_FORMATS, write_reconstruction

    assert "transforms-json" in RECONSTRUCTION_FORMATS
    rec = _reconstruction()
    path = write_reconstruction(tmp_path / "transforms.json", rec, "transforms-json", image_folder="frames")
    K, sizes, R, t, names = read_transforms_json(path)
    np.testing.assert_allclose(R, rec.R, atol=1e-14)
    np.testing.assert_allclose(t, rec.t, atol=1e-12)
    np.testing.assert_allclose(K, rec.K, atol=1e-12)
    np.testing.assert_array_equal(sizes, rec.sizes)
    assert names[0] == "frames/frame_000.png"


def test_read_takes_a_default_size_for_files_that_state_none(tmp_path):
    """NeRF-synthetic's Blender files give camera_angle_x and no w/h: the caller passes its images' size; a
    size in the file wins, and without either the reader still names what is missing."""
    rec = _reconstruction(views=2)
    c2w = camera_to_world_opengl(rec.R, rec.t)
    data = {"camera_angle_x": 2 * math.atan(320 / 500),
            "frames": [{"file_path": f"./images/{i}", "transform_matrix": c2w[i].tolist()} for i in range(2)]}
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    K, size, _, _, _ = read_transforms_json(tmp_path / "transforms.json", default_size=(640, 480))
    np.testing.assert_allclose(K[0], [[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]], atol=1e-9)
    assert tuple(size[0]) == (640, 480)
    (tmp_path / "transforms.json").write_text(json.dumps({**data, "w": 320, "h": 240}))
    _, size, _, _, _ = read_transforms_json(tmp_path / "transforms.json", default_size=(640, 480))
    assert tuple(size[0]) == (320, 240)
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(InvalidValue, match="no image size"):
        read_transforms_json(tmp_path / "transforms.json")
