"""Codecs: JSON / NPY / PNG / PLY out, and uploads in, for every value type."""

from __future__ import annotations

import io
import json

import cv2
import numpy as np
import pytest

from lab.core import (Cameras, Curve, GaussianSplats, Image, ImageSet, InvalidValue, Mesh, PointCloud, Points2D,
                      Segments2D, Segments3D)
from lab.core import codecs


def _examples():
    rng = np.random.default_rng(0)
    return [
        Image(rng.random((4, 5, 3), dtype=np.float32), "a"),
        ImageSet((Image(rng.random((4, 5), dtype=np.float32)), Image(rng.random((4, 5), dtype=np.float32)))),
        Points2D(rng.random((6, 2)), view=[0, 0, 1, 1, 2, 2], ids=[0, 1, 0, 1, 0, 1]),
        PointCloud(rng.random((5, 3)), rng.random((5, 3))),
        Cameras(np.eye(3), np.eye(3), np.zeros(3), 640, 480, dist=np.zeros(5)),
        Segments2D(rng.random((3, 2)), rng.random((3, 2))),
        Segments3D(rng.random((3, 3)), rng.random((3, 3))),
        Mesh(rng.random((4, 3)), [[0, 1, 2], [1, 2, 3]]),
        GaussianSplats(rng.random((2, 3)), np.stack([np.eye(3)] * 2), rng.random((2, 3)), rng.random(2)),
        Curve(np.arange(3), [1.0, 2.0, 3.0], kind="bar", categories=("a", "b", "c")),
    ]


@pytest.mark.parametrize("value", _examples(), ids=lambda v: type(v).__name__)
def test_json_round_trip_for_every_value_type(value):
    encoded = json.loads(json.dumps(codecs.to_json(value)))
    assert encoded["type"] == type(value).__name__
    decoded = codecs.decode_json(encoded, type(value), name="v")
    assert type(decoded) is type(value)
    for key, item in encoded.items():
        if key == "type":
            continue
        assert json.loads(json.dumps(codecs.to_json(getattr(decoded, key)))) == item


def test_npy_primary_arrays():
    cloud = PointCloud(np.arange(6.0).reshape(2, 3))
    np.testing.assert_array_equal(np.load(io.BytesIO(codecs.to_npy(cloud, name="c"))), cloud.xyz)
    images = _examples()[1]
    assert np.load(io.BytesIO(codecs.to_npy(images, name="i"))).shape == (2, 4, 5)
    assert np.load(io.BytesIO(codecs.to_npy(images, name="i", index=1))).shape == (4, 5)
    with pytest.raises(InvalidValue):
        codecs.to_npy(images, name="i", index=5)
    with pytest.raises(InvalidValue):
        codecs.to_npy("text", name="t")


def test_png_of_an_image_decodes_to_the_same_pixels():
    pixels = np.linspace(0, 1, 4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3)
    png = codecs.to_png(Image(pixels), name="im")
    back = codecs.decode_image(png, name="im")
    np.testing.assert_allclose(back.pixels, pixels, atol=1 / 255)
    disparity = np.array([[0.0, 10.0], [20.0, 40.0]])
    gray = cv2.imdecode(np.frombuffer(codecs.to_png(disparity, name="d"), np.uint8), cv2.IMREAD_UNCHANGED)
    assert gray[0, 0] == 0 and gray[1, 1] == 255
    with pytest.raises(InvalidValue):
        codecs.to_png(PointCloud(np.zeros((1, 3))), name="c")


def test_ply_round_trip_keeps_points_and_colors():
    cloud = PointCloud(np.random.default_rng(1).random((10, 3)), np.full((10, 3), 0.5))
    back = codecs.from_ply(codecs.to_ply(cloud, name="c"), name="c")
    np.testing.assert_allclose(back.xyz, cloud.xyz, atol=1e-6)
    np.testing.assert_allclose(back.colors, 128 / 255, atol=1e-6)
    mesh = _examples()[7]
    assert isinstance(codecs.from_ply(codecs.to_ply(mesh, name="m"), name="m"), Mesh)


@pytest.mark.parametrize("payload, filename, annotation, field, words", [
    (b"not an image", "x.png", ImageSet, "images", "not an image"),
    (b"{bad json", "k.json", np.ndarray, "K", "expected JSON"),
    (json.dumps([[1, 2], [3]]).encode(), "k.json", np.ndarray, "K", "cannot be read"),
    (json.dumps([[1, 2, 3]]).encode(), "p.json", Points2D, "corners", "expected shape (N, 2)"),
    (json.dumps({"xy": [[0, 0]], "bogus": 1}).encode(), "p.json", Points2D, "corners", "no field"),
    (json.dumps([[1.0, float("nan")]]).encode(), "p.json", Points2D, "corners", "NaN"),
    (b"\x93NUMPY garbage", "a.npy", np.ndarray, "K", "not a valid .npy"),
])
def test_bad_uploads_name_the_problem(payload, filename, annotation, field, words):
    with pytest.raises(InvalidValue) as info:
        codecs.decode_upload(payload, filename=filename, content_type="", annotation=annotation, name=field)
    assert info.value.field.startswith(field)
    assert words in info.value.reason


def test_uploads_of_each_kind():
    ok, png = cv2.imencode(".png", np.full((3, 4, 3), 255, np.uint8))
    images = codecs.decode_upload(png.tobytes(), filename="a.png", content_type="image/png",
                                  annotation=ImageSet, name="images")
    assert isinstance(images, ImageSet) and images[0].pixels.shape == (3, 4, 3)
    buffer = io.BytesIO()
    np.save(buffer, np.eye(3))
    K = codecs.decode_upload(buffer.getvalue(), filename="K.npy", content_type="", annotation=np.ndarray, name="K")
    np.testing.assert_array_equal(K, np.eye(3))
    points = codecs.decode_upload(b"[[1, 2], [3, 4]]", filename="", content_type="application/json",
                                  annotation=Points2D | None, name="corners")
    assert isinstance(points, Points2D) and len(points) == 2
