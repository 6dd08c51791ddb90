"""lab.data.reconstruction and lab.data.colmap: the sparse model, COLMAP text out and in exactly, pycolmap."""

import dataclasses

import numpy as np
import pycolmap
import pytest

from lab.core import InvalidValue, Points2D
from lab.data.colmap import read_colmap_text, write_colmap_text
from lab.data.reconstruction import SparseModel
from lab.geometry.rotations import look_at


def _reconstruction(views: int = 4, count: int = 30, seed: int = 0, extra_keypoints: int = 5) -> SparseModel:
    """Cameras on an arc around points; keypoints are the exact projections (OpenCV pixel convention)."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(0.0, 1.2, views)
    eyes = np.stack([5 * np.sin(angles), 0.3 * np.ones(views), -5 * np.cos(angles)], axis=1)
    R, t = look_at(eyes, np.zeros_like(eyes))
    K = np.array([[[700.0 + 10 * i, 0.0, 319.5], [0.0, 705.0, 239.5], [0.0, 0.0, 1.0]] for i in range(views)])
    K[-1] = K[0]  # two images share a camera
    X = rng.uniform(-1.0, 1.0, (count, 3))
    keypoints, tracks = [], [[] for _ in range(count)]
    for i in range(views):
        Xc = X @ R[i].T + t[i]
        uv = Xc[:, :2] / Xc[:, 2:] @ K[i, :2, :2].T + K[i, :2, 2]
        seen = np.flatnonzero(rng.random(count) < 0.8)
        # keypoints in random order, some without a 3D point
        order = rng.permutation(len(seen) + extra_keypoints)
        points = np.concatenate([uv[seen], rng.uniform(0, 640, (extra_keypoints, 2))])[np.argsort(order)]
        ids = np.concatenate([seen, -np.ones(extra_keypoints, dtype=int)])[np.argsort(order)]
        keypoints.append(points)
        for k, j in enumerate(ids):
            if j >= 0:
                tracks[j].append((i, k))
    return SparseModel.from_tracks(K=K, sizes=np.tile([640, 480], (views, 1)), R=R, t=t,
                                   names=tuple(f"view_{i:02d}.png" for i in range(views)),
                                   keypoints=tuple(keypoints),
                                   points=X, colors=rng.integers(0, 256, (count, 3)),
                                   errors=rng.uniform(0, 1, count),
                                   tracks=tuple(np.array(tr, dtype=np.int64).reshape(-1, 2) for tr in tracks))


def _fields(rec: SparseModel) -> dict:
    """The arguments of :meth:`SparseModel.from_tracks` that give ``rec``."""
    return dict(K=rec.K, sizes=rec.sizes, R=rec.R, t=rec.t, names=rec.names, keypoints=rec.image_keypoints,
                points=rec.points, colors=rec.colors, errors=rec.errors, tracks=rec.tracks)


# --- SparseModel --------------------------------------------------------------------------------
def test_reconstruction_smoke_dtypes_and_properties():
    rec = _reconstruction()
    assert len(rec) == 4 and rec.registered.all()
    assert rec.colors.dtype == np.uint8 and rec.sizes.dtype == np.int64 and rec.tracks[0].dtype == np.int64
    np.testing.assert_allclose(rec.centers, -np.einsum("nji,nj->ni", rec.R, rec.t))
    assert rec.mean_track_length == pytest.approx(np.mean([len(tr) for tr in rec.tracks]))
    assert rec.equals(rec) and not rec.equals(_reconstruction(seed=1))
    assert rec.compact().equals(rec)  # a model made from tracks is in the form files hold
    assert SparseModel.from_tracks(**_fields(rec)).equals(rec)
    cameras = rec.cameras(image="images")
    assert len(cameras) == 4 and (cameras.width, cameras.height) == (640, 480)
    np.testing.assert_allclose(cameras.centers, rec.centers)
    cloud = rec.point_cloud()
    np.testing.assert_array_equal(cloud.xyz, rec.points)
    np.testing.assert_allclose(cloud.colors * 255, rec.colors)


@pytest.mark.parametrize("field, value, message", [
    ("K", np.zeros((4, 3)), "K"),
    ("sizes", np.zeros((4, 2)), "positive"),
    ("t", np.zeros((3, 3)), r"expected shape \(4, 3\)"),
    ("names", ("a", "b", "c"), "4 non-empty"),
    ("colors", np.full((30, 3), 300), r"\[0, 255\]"),
    ("errors", np.full(30, np.nan), "NaN"),
    ("tracks", (), "30 tracks"),
])
def test_reconstruction_rejects_bad_fields(field, value, message):
    fields = _fields(_reconstruction())
    fields[field] = value
    with pytest.raises(InvalidValue, match=message):
        SparseModel.from_tracks(**fields)


def test_a_model_checks_its_tracks_and_keypoints():
    rec = _reconstruction()
    fields = {f.name: getattr(rec, f.name) for f in dataclasses.fields(SparseModel)}
    with pytest.raises(InvalidValue, match="its own track"):
        SparseModel(**{**fields, "point_tracks": np.zeros(len(rec.points), dtype=int)})
    with pytest.raises(InvalidValue, match="track_of"):
        SparseModel(**{**fields, "track_of": rec.track_of[:-1]})
    with pytest.raises(InvalidValue, match=r"views must lie in \[0, 4\)"):
        SparseModel(**{**fields, "keypoints": Points2D(rec.keypoints.xy, view=rec.view + 1)})
    with pytest.raises(InvalidValue, match="a view per keypoint"):
        SparseModel(**{**fields, "keypoints": Points2D(rec.keypoints.xy)})
    # a view left unregistered keeps its keypoints but observes nothing, and is not written
    half = SparseModel(**{**fields, "registered": np.array([True, True, False, True])})
    _, views, _ = half.observations()
    assert 2 not in views and len(half.compact()) == 3
    assert half.compact().names == tuple(rec.names[v] for v in (0, 1, 3))


def test_reconstruction_rejects_tracks_out_of_range():
    rec = _reconstruction()
    tracks = list(rec.tracks)
    tracks[0] = np.array([[0, 10_000]])
    with pytest.raises(InvalidValue, match=r"tracks\[0\]"):
        SparseModel.from_tracks(**{**_fields(rec), "tracks": tuple(tracks)})


# --- our writer and reader ------------------------------------------------------------------------
def test_write_creates_the_three_files(tmp_path):
    folder = write_colmap_text(tmp_path / "sparse" / "0", _reconstruction())
    assert sorted(p.name for p in folder.iterdir()) == ["cameras.txt", "images.txt", "points3D.txt"]
    cameras = [line for line in (folder / "cameras.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(cameras) == 3  # four images, two share K and size
    assert cameras[0].split()[:4] == ["1", "PINHOLE", "640", "480"]
    assert cameras[0].split()[6:] == ["320.0", "240.0"]  # principal point + 0.5 (COLMAP's pixel centres)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_round_trip_is_exact(tmp_path, seed):
    rec = _reconstruction(seed=seed)
    back = read_colmap_text(write_colmap_text(tmp_path, rec))
    assert back.equals(rec)


def test_round_trip_is_exact_for_awkward_numbers(tmp_path):
    """Pixels whose +0.5 is not exactly invertible in floating point (tiny, negative, many digits)."""
    rec = _reconstruction(views=2, count=3)
    keypoints = list(rec.image_keypoints)
    awkward = np.array([1e-20, -0.25, 0.1, 1 / 3, 123456.789012345678, -5e-324, 2.0**-30,
                        0.49999999999999994])
    keypoints[0] = np.concatenate([rec.image_keypoints[0], np.stack([awkward, awkward[::-1]], axis=1)])
    K = rec.K.copy()
    K[0, 0, 2], K[1, 1, 2] = 0.1, 1e-17
    rec = SparseModel.from_tracks(K, rec.sizes, rec.R, rec.t, rec.names, tuple(keypoints), rec.points * np.pi,
                                  rec.colors, rec.errors / 3, rec.tracks)
    assert read_colmap_text(write_colmap_text(tmp_path, rec)).equals(rec)


def test_round_trip_without_points_or_keypoints(tmp_path):
    rec = _reconstruction(views=2, count=3)
    empty = SparseModel.from_tracks(rec.K, rec.sizes, rec.R, rec.t, rec.names,
                                    (np.zeros((0, 2)), np.zeros((0, 2))),
                                    np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), ())
    assert read_colmap_text(write_colmap_text(tmp_path, empty)).equals(empty)


# --- pycolmap reads ours, we read pycolmap's --------------------------------------------------------
def test_pycolmap_reads_what_we_write(tmp_path):
    rec = _reconstruction()
    model = pycolmap.Reconstruction(str(write_colmap_text(tmp_path, rec)))
    assert model.num_reg_images() == 4 and model.num_points3D() == len(rec.points)
    for i in range(len(rec)):
        image = model.images[i + 1]
        assert image.name == rec.names[i]
        pose = image.cam_from_world()
        np.testing.assert_allclose(pose.rotation.matrix(), rec.R[i], atol=1e-15)
        np.testing.assert_array_equal(pose.translation, rec.t[i])
        fx, fy, cx, cy = image.camera.params
        assert (fx, fy) == (rec.K[i, 0, 0], rec.K[i, 1, 1])
        np.testing.assert_allclose([cx, cy], rec.K[i, :2, 2] + 0.5, rtol=1e-15)
        xy = np.array([p.xy for p in image.points2D])
        np.testing.assert_allclose(xy, rec.image_keypoints[i] + 0.5, rtol=1e-15)
    for j in range(len(rec.points)):
        point = model.points3D[j + 1]
        np.testing.assert_array_equal(point.xyz, rec.points[j])
        np.testing.assert_array_equal(point.color, rec.colors[j])
        elements = sorted((e.image_id - 1, e.point2D_idx) for e in point.track.elements)
        assert elements == sorted(map(tuple, rec.tracks[j].tolist()))
    # the keypoints are exact projections: COLMAP's own projection agrees once the 0.5 px shift is right
    model.update_point_3d_errors()
    assert model.compute_mean_reprojection_error() < 1e-9


def test_we_read_what_pycolmap_writes(tmp_path):
    rec = _reconstruction(seed=3)
    model = pycolmap.Reconstruction(str(write_colmap_text(tmp_path / "ours", rec)))
    model.transform(pycolmap.Sim3d(2.0, pycolmap.Rotation3d(np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm(
        [0.1, 0.2, 0.3, 0.9])), np.array([1.0, -2.0, 0.5])))
    (tmp_path / "theirs").mkdir()
    model.write_text(str(tmp_path / "theirs"))
    back = read_colmap_text(tmp_path / "theirs")
    assert back.names == rec.names
    for i in range(len(rec)):
        pose = model.images[i + 1].cam_from_world()
        np.testing.assert_allclose(back.R[i], pose.rotation.matrix(), atol=1e-15)
        np.testing.assert_array_equal(back.t[i], pose.translation)
        # 17 digits: exact again
        np.testing.assert_array_equal(back.image_keypoints[i], rec.image_keypoints[i])
    np.testing.assert_array_equal(back.K, rec.K)
    np.testing.assert_array_equal(back.points,
                                  np.array([model.points3D[j + 1].xyz for j in range(len(rec.points))]))
    assert all(np.array_equal(a, b) for a, b in zip(back.tracks, rec.tracks, strict=True))


def test_we_read_simple_pinhole_and_zero_distortion_models(tmp_path):
    write_colmap_text(tmp_path, _reconstruction(views=3, count=4))  # images 0 and 2 share camera 1
    (tmp_path / "cameras.txt").write_text("1 SIMPLE_PINHOLE 640 480 700 320 240\n"
                                          "2 SIMPLE_RADIAL 640 480 710 320 240 0\n")
    back = read_colmap_text(tmp_path)
    np.testing.assert_array_equal(back.K[0], [[700, 0, 319.5], [0, 700, 239.5], [0, 0, 1]])
    np.testing.assert_array_equal(back.K[2], back.K[0])
    assert back.K[1, 1, 1] == 710


# --- errors -----------------------------------------------------------------------------------------
def test_write_rejects_what_colmap_cannot_hold(tmp_path):
    rec = _reconstruction(views=2, count=4)
    K = rec.K.copy()
    K[0, 0, 1] = 0.5
    skewed = SparseModel.from_tracks(**{**_fields(rec), "K": K})
    with pytest.raises(InvalidValue, match="skew"):
        write_colmap_text(tmp_path, skewed)
    spaced = SparseModel.from_tracks(**{**_fields(rec), "names": ("a b.png", "c.png")})
    with pytest.raises(InvalidValue, match="whitespace"):
        write_colmap_text(tmp_path, spaced)
    twice = SparseModel.from_tracks(**{**_fields(rec), "names": ("a.png", "a.png")})
    with pytest.raises(InvalidValue, match="unique"):
        write_colmap_text(tmp_path, twice)
    # a keypoint in two tracks cannot even be a model: it observes one 3D point (COLMAP's POINTS2D too)
    with pytest.raises(InvalidValue, match="one 3D point per keypoint"):
        SparseModel.from_tracks(**{**_fields(rec), "tracks": (rec.tracks[0],) * len(rec.tracks)})
    assert not (tmp_path / "images.txt").exists()


def test_read_names_the_file_and_line_of_a_malformed_entry(tmp_path):
    write_colmap_text(tmp_path, _reconstruction(views=2, count=4))
    lines = (tmp_path / "points3D.txt").read_text().splitlines()
    lines[4] = "2 0.1 0.2"  # line 5: too few fields
    (tmp_path / "points3D.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InvalidValue, match=r"points3D\.txt line 5"):
        read_colmap_text(tmp_path)


def test_read_rejects_distortion_and_unknown_ids(tmp_path):
    write_colmap_text(tmp_path, _reconstruction(views=2, count=4))
    original = (tmp_path / "cameras.txt").read_text()
    distorted = original.replace("PINHOLE 640 480 700.0 705.0 320.0 240.0",
                                 "OPENCV 640 480 700.0 705.0 320.0 240.0 0.1 0 0 0")
    (tmp_path / "cameras.txt").write_text(distorted)
    with pytest.raises(InvalidValue, match="distortion"):
        read_colmap_text(tmp_path)
    (tmp_path / "cameras.txt").write_text(original.replace("\n1 PINHOLE", "\n7 PINHOLE"))
    with pytest.raises(InvalidValue, match=r"camera id 1 is not in cameras\.txt"):
        read_colmap_text(tmp_path)


def test_read_rejects_a_track_that_disagrees_with_images(tmp_path):
    write_colmap_text(tmp_path, _reconstruction(views=2, count=4, extra_keypoints=0))
    lines = (tmp_path / "points3D.txt").read_text().splitlines()
    fields = lines[3].split()
    fields[-1] = str((int(fields[-1]) + 1) % 3)  # point the last observation at another keypoint
    lines[3] = " ".join(fields)
    (tmp_path / "points3D.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InvalidValue, match=r"does not match images\.txt"):
        read_colmap_text(tmp_path)


def test_read_rejects_a_missing_folder_or_file(tmp_path):
    with pytest.raises(InvalidValue, match="no such folder"):
        read_colmap_text(tmp_path / "nowhere")
    with pytest.raises(InvalidValue, match=r"no cameras\.txt"):
        read_colmap_text(tmp_path)


# --- the export registry ---------------------------------------------------------------------------
def test_export_registry_writes_colmap(tmp_path):
    from lab.data.exports import RECONSTRUCTION_FORMATS, write_reconstruction

    assert "colmap" in RECONSTRUCTION_FORMATS
    rec = _reconstruction()
    assert read_colmap_text(write_reconstruction(tmp_path / "model", rec, "colmap")).equals(rec)
    with pytest.raises(InvalidValue, match="unknown format"):
        write_reconstruction(tmp_path / "x", rec, "bundler")
    with pytest.raises(InvalidValue, match="not a ndarray"):
        write_reconstruction(tmp_path / "x", np.zeros(3), "colmap")
    # names become file names: whitespace is replaced, a repeated name is prefixed with its view
    named = SparseModel.from_tracks(**{**_fields(rec), "names": ("a b.png", "c.png", "a_b.png", "d.png")})
    back = read_colmap_text(write_reconstruction(tmp_path / "named", named, "colmap"))
    assert back.names == ("a_b.png", "c.png", "002_a_b.png", "d.png")
