"""Reading state values as JSON, NPY, PNG and PLY, and uploading inputs (raw, multipart, append),
with every bad upload refused by a 4xx naming the field and leaving the session as it was."""

from __future__ import annotations

import io
import json

import cv2
import numpy as np
import pytest
import trimesh
from api_helpers import UPLOAD_LIMIT, assert_error, new_session, snapshot

from lab.api.values import check_known_value, select_index
from lab.core import InvalidValue, PointCloud


def _png(value: int = 128, shape=(4, 6, 3)) -> bytes:
    return cv2.imencode(".png", np.full(shape, value, np.uint8))[1].tobytes()


def _npy(array) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array), allow_pickle=True)
    return buffer.getvalue()


@pytest.fixture
def lifted(client):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/run-until/lift")
    return sid


# --- reading ----------------------------------------------------------------------------------------
def test_json_of_a_typed_value_and_of_one_view(client, store, lifted):
    body = client.get(f"/api/sessions/{lifted}/values/images").json()
    assert body["type"] == "ImageSet" and len(body["images"]) == 3
    assert body["images"][0]["type"] == "Image" and body["images"][0]["name"] == "g0"
    one = client.get(f"/api/sessions/{lifted}/values/images", params={"index": 1}).json()
    assert one["name"] == "g1"
    np.testing.assert_allclose(one["pixels"], store.get(lifted).get("images")[1].pixels, atol=1e-6)


def test_json_of_an_array_and_of_one_row(client, store, lifted):
    means = store.get(lifted).get("means")
    assert client.get(f"/api/sessions/{lifted}/values/means").json() == pytest.approx(means.tolist())
    assert client.get(f"/api/sessions/{lifted}/values/means", params={"index": 2}).json() == pytest.approx(means[2])


def test_npy_of_images_points_and_arrays(client, store, lifted):
    session = store.get(lifted)
    response = client.get(f"/api/sessions/{lifted}/values/images", params={"format": "npy"})
    assert response.headers["content-type"] == "application/x-npy"
    stacked = np.load(io.BytesIO(response.content))
    assert stacked.shape == (3, 16, 16) and stacked.dtype == np.float32
    view = np.load(io.BytesIO(client.get(f"/api/sessions/{lifted}/values/images",
                                         params={"format": "npy", "index": 2}).content))
    np.testing.assert_array_equal(view, session.get("images")[2].pixels)
    xyz = np.load(io.BytesIO(client.get(f"/api/sessions/{lifted}/values/cloud", params={"format": "npy"}).content))
    np.testing.assert_array_equal(xyz, session.get("cloud").xyz)


def test_png_of_one_view(client, store, lifted):
    response = client.get(f"/api/sessions/{lifted}/values/noisy", params={"format": "png", "index": 0})
    assert response.headers["content-type"] == "image/png"
    assert 'filename="noisy_0.png"' in response.headers["content-disposition"]
    decoded = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_UNCHANGED)
    expected = np.round(store.get(lifted).get("noisy")[0].pixels * 255)
    np.testing.assert_allclose(decoded, expected, atol=1)


def test_ply_of_a_point_cloud(client, store, lifted):
    response = client.get(f"/api/sessions/{lifted}/values/cloud", params={"format": "ply"})
    assert response.headers["content-type"] == "application/ply"
    loaded = trimesh.load(io.BytesIO(response.content), file_type="ply")
    np.testing.assert_allclose(loaded.vertices, store.get(lifted).get("cloud").xyz)


@pytest.mark.parametrize("name, params, status, field", [
    ("nothing", {}, 404, "value"),
    ("images", {"format": "gif"}, 422, "format"),
    ("means", {"format": "png"}, 422, "format"),
    ("images", {"format": "ply"}, 422, "format"),
    ("cloud", {"format": "png"}, 422, "format"),
    ("images", {"index": 3}, 422, "index"),
    ("images", {"index": -1}, 422, "index"),
    ("images", {"index": "first"}, 422, "index"),
    ("cloud", {"index": 0}, 422, "index"),
])
def test_bad_read_is_4xx_naming_the_field(client, lifted, name, params, status, field):
    before = snapshot(client, lifted)
    assert_error(client.get(f"/api/sessions/{lifted}/values/{name}", params=params), status, field)
    assert snapshot(client, lifted) == before


def test_reading_a_value_not_computed_yet_says_which_step_makes_it(client):
    sid = new_session(client)
    body = assert_error(client.get(f"/api/sessions/{sid}/values/cloud"), 404, "value", "not_found")
    assert "run step 'lift' first" in body["reason"]


def test_select_index_parts():
    from lab.core import Cameras, Points2D, Segments2D

    points = Points2D(np.arange(8.0).reshape(4, 2), view=np.array([0, 1, 1, 0]))
    np.testing.assert_array_equal(select_index(points, 1, "corners").xy, [[2, 3], [4, 5]])
    segments = Segments2D(np.zeros((3, 2)), np.ones((3, 2)), view=np.array([2, 0, 2]))
    assert len(select_index(segments, 2, "residuals")) == 2
    cameras = Cameras(np.stack([np.eye(3)] * 2), np.stack([np.eye(3)] * 2), np.array([[0, 0, 1.0], [0, 0, 2.0]]), 4, 3)
    one = select_index(cameras, 1, "cameras")
    assert len(one) == 1 and one.t[0, 2] == 2.0
    with pytest.raises(InvalidValue) as caught:
        select_index(Points2D(np.zeros((2, 2))), 0, "x")
    assert caught.value.field == "index"


# --- uploading -------------------------------------------------------------------------------------
def test_upload_raw_image_replaces_an_image_set_and_invalidates_downstream(client, store, lifted):
    response = client.put(f"/api/sessions/{lifted}/values/images", content=_png(200),
                          headers={"content-type": "image/png"}, params={"filename": "mine.png"})
    assert response.status_code == 200
    body = response.json()
    assert body["type"] == "ImageSet" and body["count"] == 1
    assert body["invalidated"] == ["add_noise", "mean_intensity", "lift"]
    assert body["steps"] == {"add_noise": "ready", "mean_intensity": "blocked", "lift": "blocked"}
    assert body["has_truth"] is False  # the toy's truth described the dataset's images
    image = store.get(lifted).get("images")[0]
    assert image.name == "mine.png" and image.pixels.shape == (4, 6, 3)
    np.testing.assert_allclose(image.pixels, 200 / 255, atol=1e-6)
    assert set(client.get(f"/api/sessions/{lifted}").json()["values"]) == {"images"}


def test_append_adds_a_view(client, store):
    sid = new_session(client)
    body = client.put(f"/api/sessions/{sid}/values/images", params={"append": "true", "filename": "extra.png"},
                      content=_png(), headers={"content-type": "image/png"}).json()
    assert body["count"] == 4
    assert store.get(sid).get("images").names == ("g0", "g1", "g2", "extra.png")


def test_multipart_upload_of_several_photos_makes_a_set(client, store):
    sid = new_session(client)
    files = [("file", ("a.png", _png(10), "image/png")), ("file", ("b.jpg", cv2.imencode(".jpg", np.zeros((5, 5, 3), np.uint8))[1].tobytes(), "image/jpeg"))]
    body = client.put(f"/api/sessions/{sid}/values/images", files=files).json()
    assert body["count"] == 2
    assert store.get(sid).get("images").names == ("a.png", "b.jpg")
    body = client.put(f"/api/sessions/{sid}/values/images", params={"append": "true"},
                      files={"file": ("c.png", _png(), "image/png")}).json()
    assert body["count"] == 3


def test_upload_array_as_json_or_npy_then_run_on_it(client, store):
    sid = new_session(client)
    body = client.put(f"/api/sessions/{sid}/values/means", json=[0.25, 0.5]).json()
    assert body["type"] == "ndarray" and body["shape"] == [2]
    assert body["has_truth"] is True  # a step's output was replaced: the dataset's truth still holds
    record = client.post(f"/api/sessions/{sid}/steps/lift").json()
    assert record["status"] == "ok"
    np.testing.assert_array_equal(store.get(sid).get("cloud").xyz[:, 0], [0.25, 0.5])
    body = client.put(f"/api/sessions/{sid}/values/means", content=_npy(np.array([1, 2, 3]))).json()
    assert body["shape"] == [3] and body["invalidated"] == ["lift"]
    np.testing.assert_array_equal(store.get(sid).get("means"), [1, 2, 3])


def test_json_round_trip_of_an_image_set(client, store, lifted):
    exported = client.get(f"/api/sessions/{lifted}/values/noisy").content
    original = store.get(lifted).get("noisy")
    response = client.put(f"/api/sessions/{lifted}/values/noisy", content=exported,
                          headers={"content-type": "application/json"})
    assert response.status_code == 200
    for a, b in zip(original.images, store.get(lifted).get("noisy").images):
        np.testing.assert_allclose(a.pixels, b.pixels, atol=1e-6)
        assert a.name == b.name


def test_upload_point_cloud_as_ply_raw_or_multipart(client, store):
    sid = new_session(client, "gated")
    xyz = np.array([[0.0, 0, 0], [2, 0, 0], [0, 4, 0], [2, 4, 6]])
    ply = trimesh.PointCloud(xyz).export(file_type="ply")
    body = client.put(f"/api/sessions/{sid}/values/cloud", content=ply,
                      headers={"content-type": "application/octet-stream"}).json()
    assert body["type"] == "PointCloud"
    record = client.post(f"/api/sessions/{sid}/steps/centroid").json()
    assert record["status"] == "ok"
    np.testing.assert_allclose(store.get(sid).get("center"), [1, 2, 1.5])
    body = client.put(f"/api/sessions/{sid}/values/cloud", files={"file": ("c.ply", ply, "application/ply")}).json()
    assert body["type"] == "PointCloud"
    body = client.put(f"/api/sessions/{sid}/values/cloud", json={"xyz": xyz.tolist()}).json()
    assert body["type"] == "PointCloud"


def test_upload_camera_matrix_then_run_on_it(client, store):
    sid = new_session(client, "gated")
    K = [[800.0, 0, 320], [0, 780, 240], [0, 0, 1]]
    assert client.put(f"/api/sessions/{sid}/values/K", json=K).status_code == 200
    client.post(f"/api/sessions/{sid}/steps/focal")
    np.testing.assert_array_equal(store.get(sid).get("focal"), [800, 780])


@pytest.mark.parametrize("K, fragment", [
    (np.eye(4).tolist(), "expected shape (3, 3)"),
    ([1.0, 2.0, 3.0], "expected shape (3, 3)"),
    ([[800.0, 0, 320], [5, 780, 240], [0, 0, 1]], "upper triangular"),
    ([[800.0, 0, 320], [0, 780, 240], [0, 0, 2]], "K[2, 2] = 1"),
    ([[-800.0, 0, 320], [0, 780, 240], [0, 0, 1]], "positive"),
    ([["a", 0, 0], [0, 1, 0], [0, 0, 1]], "cannot be read"),
    ([[800.0, 0], [0, 780, 240], [0, 0, 1]], "cannot be read"),
])
def test_bad_camera_matrix_is_422_and_changes_nothing(client, K, fragment):
    sid = new_session(client, "gated")
    before = snapshot(client, sid)
    body = assert_error(client.put(f"/api/sessions/{sid}/values/K", json=K), 422, "K", "invalid_value")
    assert fragment in body["reason"]
    assert snapshot(client, sid) == before


def test_check_known_value_shapes():
    check_known_value("dist", np.zeros(5))
    check_known_value("homographies", np.stack([np.eye(3)] * 4))
    check_known_value("anything", np.zeros((2, 7)))  # no rule: any numeric array
    for name, value in [("dist", np.zeros(4)), ("homographies", np.eye(3)), ("board_points", np.zeros((5, 2))),
                        ("means", np.array([1.0, np.nan])), ("means", np.array([1 + 2j]))]:
        with pytest.raises(InvalidValue) as caught:
            check_known_value(name, value)
        assert caught.value.field == name


@pytest.mark.parametrize("name, kwargs, field, fragment", [
    ("images", {"content": b"not an image at all", "headers": {"content-type": "image/png"}}, "images", "not an image"),
    ("images", {"content": _png()[:40], "headers": {"content-type": "image/png"}}, "images", "not an image"),
    ("images", {"files": {"file": ("notes.txt", b"hello", "text/plain")}}, "images", "not an image"),
    ("means", {"content": b"[1, 2", "headers": {"content-type": "application/json"}}, "means", "expected JSON"),
    ("means", {"content": b'["a", "b"]', "headers": {"content-type": "application/json"}}, "means", "cannot be read"),
    ("means", {"content": b"[[1], [1, 2]]", "headers": {"content-type": "application/json"}}, "means", "cannot be read"),
    ("means", {"content": b"[1, NaN]", "headers": {"content-type": "application/json"}}, "means", "NaN"),
    ("means", {"content": _npy(np.array([1.0, np.inf]))}, "means", "NaN or infinite"),
    ("means", {"content": _npy(np.array(["a", "b"]))}, "means", "numeric"),
    ("means", {"content": _npy(np.array([{}, 1], dtype=object))}, "means", "not a valid .npy"),
    ("means", {"content": b"\x93NUMPY garbage"}, "means", "not a valid .npy"),
    ("means", {"content": b""}, "body", "empty"),
    ("means", {"files": {"file": ("empty.npy", b"", "application/octet-stream")}}, "file", "empty"),
    ("means", {"files": [("file", ("a.json", b"[1]", "application/json")),
                         ("file", ("b.json", b"[2]", "application/json"))]}, "file", "one file"),
    ("means", {"content": b'--xyz\r\nContent-Disposition: form-data; name="note"\r\n\r\nhi\r\n--xyz--\r\n',
               "headers": {"content-type": "multipart/form-data; boundary=xyz"}}, "file", "no file part"),
    ("means", {"content": b"garbage", "headers": {"content-type": "multipart/form-data; boundary=xyz"}},
     "file", "malformed multipart"),
    ("means", {"content": b"garbage", "headers": {"content-type": "multipart/form-data"}}, "file", "malformed multipart"),
    ("means", {"params": {"append": "true"}, "json": [1.0]}, "append", "only image sets"),
])
def test_bad_upload_is_4xx_naming_the_field_and_changes_nothing(client, lifted, name, kwargs, field, fragment):
    before = snapshot(client, lifted)
    body = assert_error(client.put(f"/api/sessions/{lifted}/values/{name}", **kwargs), 422, field)
    assert fragment in body["reason"], body
    assert snapshot(client, lifted) == before


def test_ply_upload_for_images_is_refused(client):
    sid = new_session(client)
    before = snapshot(client, sid)
    ply = trimesh.PointCloud(np.zeros((3, 3))).export(file_type="ply")
    assert_error(client.put(f"/api/sessions/{sid}/values/images", content=ply), 422, "images", "invalid_value")
    assert snapshot(client, sid) == before


def test_mesh_ply_for_a_point_cloud_input_is_refused(client):
    sid = new_session(client, "gated")
    mesh = trimesh.Trimesh(np.eye(3), [[0, 1, 2]]).export(file_type="ply")
    body = assert_error(client.put(f"/api/sessions/{sid}/values/cloud", content=mesh), 422, "cloud")
    assert "PointCloud" in body["reason"] and "Mesh" in body["reason"]


def test_upload_of_a_value_no_step_reads_is_refused(client, lifted):
    before = snapshot(client, lifted)
    body = assert_error(client.put(f"/api/sessions/{lifted}/values/cloud", json=[[0, 0, 0]]), 404, "value")
    assert "no step reads 'cloud'" in body["reason"] and "means" in body["reason"]
    body = assert_error(client.put(f"/api/sessions/{lifted}/values/colour", json=[1]), 404, "value")
    assert "no value 'colour'" in body["reason"]
    assert snapshot(client, lifted) == before


def test_too_large_upload_is_413_before_it_is_read(client, lifted):
    before = snapshot(client, lifted)
    big = b"\0" * (UPLOAD_LIMIT + 1)
    body = assert_error(client.put(f"/api/sessions/{lifted}/values/images", content=big,
                                   headers={"content-type": "image/png"}), 413, "body", "capacity")
    assert str(UPLOAD_LIMIT) in body["reason"]

    def chunked():  # no Content-Length: the limit is enforced while reading
        for _ in range(UPLOAD_LIMIT // 10_000 + 2):
            yield b"\0" * 10_000

    assert_error(client.put(f"/api/sessions/{lifted}/values/images", content=chunked()), 413, "body", "capacity")
    assert_error(client.put(f"/api/sessions/{lifted}/values/images", files={"file": ("a.png", big, "image/png")}),
                 413, "body", "capacity")
    controls = json.dumps({"sigma": 0.1, "pad": "x" * UPLOAD_LIMIT})
    assert_error(client.post(f"/api/sessions/{lifted}/steps/add_noise", content=controls,
                             headers={"content-type": "application/json"}), 413, "body", "capacity")
    assert snapshot(client, lifted) == before


def test_chunked_upload_under_the_limit_is_accepted(client, store):
    sid = new_session(client)
    payload = _png(90)

    def chunked():
        for start in range(0, len(payload), 7):
            yield payload[start:start + 7]

    response = client.put(f"/api/sessions/{sid}/values/images", content=chunked(), headers={"content-type": "image/png"})
    assert response.status_code == 200
    np.testing.assert_allclose(store.get(sid).get("images")[0].pixels, 90 / 255, atol=1e-6)


def test_point_cloud_type_survives_upload(client, store):
    sid = new_session(client, "gated")
    client.put(f"/api/sessions/{sid}/values/cloud", json=[[1.0, 2.0, 3.0]])
    assert isinstance(store.get(sid).get("cloud"), PointCloud)
