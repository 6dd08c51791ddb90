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


# --- budgets: image sizes from headers, JSON size and depth ----------------------------------------------
_HEADER_CASES = [(".png", "u8"), (".jpg", "u8"), (".bmp", "u8"), (".webp", "u8"), (".tif", "u8"), (".pgm", "grey"),
                 (".ppm", "u8"), (".pbm", "grey"), (".pam", "u8"), (".pfm", "float"), (".ras", "u8"), (".hdr", "float"),
                 (".jp2", "u8")]


@pytest.mark.parametrize("suffix, kind", _HEADER_CASES, ids=[s for s, _ in _HEADER_CASES])
def test_image_size_reads_each_format_opencv_writes_from_its_header(suffix, kind):
    pixels = (np.random.default_rng(0).random((37, 53, 3)) * 255).astype(np.uint8)
    if kind == "grey":
        pixels = pixels[:, :, 0]
    elif kind == "float":
        pixels = pixels.astype(np.float32) / 255
    ok, encoded = cv2.imencode(suffix, pixels)
    assert ok
    assert codecs.image_size(io.BytesIO(encoded.tobytes())) == (53, 37)


def test_image_size_of_progressive_jpeg_gif_and_truncated_or_foreign_files():
    pixels = np.zeros((37, 53, 3), np.uint8)
    ok, progressive = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    assert codecs.image_size(io.BytesIO(progressive.tobytes())) == (53, 37)
    gif = b"GIF89a" + (53).to_bytes(2, "little") + (37).to_bytes(2, "little") + b"\x00" * 20
    assert codecs.image_size(io.BytesIO(gif)) == (53, 37)
    for junk in [b"", b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff", b"\xff\xd8" + b"\xff" * 100_000,
                 b"II*\x00\xff\xff\xff\xff", b"BM", b"P6 12", b"hello", b'{"pixels": []}']:
        assert codecs.image_size(io.BytesIO(junk)) is None, junk[:12]


def test_an_image_over_the_pixel_budget_is_refused_before_decoding(monkeypatch):
    from lab.core import CapacityExceeded, budgets

    ok, encoded = cv2.imencode(".png", np.zeros((30, 40), np.uint8))
    monkeypatch.setattr(budgets, "MAX_IMAGE_PIXELS", 1000)
    with pytest.raises(CapacityExceeded, match="40 x 30 pixels") as refused:
        codecs.decode_image(encoded.tobytes(), name="photo", what="'p.png'")
    assert refused.value.field == "photo" and "'p.png'" in refused.value.reason
    monkeypatch.setattr(budgets, "MAX_IMAGE_PIXELS", 1200)
    assert codecs.decode_image(encoded.tobytes(), name="photo").pixels.shape == (30, 40)


def test_image_from_cv2_matches_the_plain_conversion_and_leaves_its_input_alone():
    rng = np.random.default_rng(1)
    bgr = (rng.random((6, 7, 3)) * 255).astype(np.uint8)
    for decoded in [bgr, bgr[:, :, 0], np.dstack([bgr, bgr[:, :, :1]]), bgr.astype(np.uint16) * 257,
                    rng.random((6, 7, 3)) * 2 - 0.5, (rng.random((6, 7)) * 2).astype(np.float32)]:
        scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(decoded.dtype, 1.0)
        expected = decoded.astype(np.float32) / scale
        if expected.ndim == 3:
            expected = cv2.cvtColor(expected[:, :, :3], cv2.COLOR_BGR2RGB)
        before = decoded.copy()
        assert np.array_equal(codecs.image_from_cv2(decoded).pixels, np.clip(expected, 0, 1))
        assert np.array_equal(decoded, before)


def test_json_numbers_counts_without_building_the_json():
    value = ImageSet((Image(np.zeros((4, 5), np.float32), "a"), Image(np.zeros((2, 3, 3), np.float32), "b")))
    assert codecs.json_numbers(value) == 20 + 18
    assert codecs.json_numbers({"a": [1, 2.5, None, "text"], "b": np.zeros(3)}) == 5


def test_json_answers_over_the_budget_point_to_npy_and_png(monkeypatch):
    from lab.core import budgets

    monkeypatch.setattr(budgets, "MAX_JSON_NUMBERS", 10)
    codecs.check_json_answer(np.zeros(10), name="small")
    with pytest.raises(InvalidValue, match="format=npy or format=png") as refused:
        codecs.check_json_answer(Image(np.zeros((4, 4), np.float32)), name="photo")
    assert refused.value.field == "format"
    with pytest.raises(InvalidValue, match="read it as format=npy, or"):
        codecs.check_json_answer(np.zeros(11), name="array")


def test_json_depth_ignores_brackets_in_strings_and_refuses_deep_uploads():
    assert codecs.json_depth(b'{"a": [[1, 2], {"b": "[[[[\\"]]"}]}') == 3
    assert codecs.json_depth(b"[" * 3_000_000 + b"]" * 3_000_000) == 3_000_000
    with pytest.raises(InvalidValue, match="nests 100 levels"):
        codecs.decode_upload(b"[" * 100 + b"]" * 100, filename="x.json", content_type="application/json",
                             annotation=np.ndarray, name="K")
