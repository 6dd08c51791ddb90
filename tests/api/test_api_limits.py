"""Bounded inputs: pixel budgets read from image headers, dataset and JSON budgets, nesting, submissions, data root.

Each attack is refused with a JSON 4xx naming the field at fault, and (where memory is the point)
the test process's resident memory, read from ``/proc/self/status``, grows by less than 200 MB
around the request.
"""

from __future__ import annotations

import asyncio
import functools
import io
import os
import struct
import sys
import time
import zlib
from pathlib import Path
from typing import Any, Callable

import cv2
import httpx
import numpy as np
import pytest
from api_helpers import PIPELINES, assert_error, make_client, new_session
from fastapi.testclient import TestClient

from lab.api import create_app
from lab.api.lessons import build_app
from lab.core import SessionStore, budgets
from lab.core.errors import CapacityExceeded, Forbidden
from lab.data.files import read_images
from lab.lessons.format import LessonCatalog
from lab.lessons.service import LessonService
from lab.lessons.store import SubmissionQueue

MB = 2**20
FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
LESSON_FIXTURES = FIXTURES / "lessons"
if str(FIXTURES) not in sys.path:  # the toy lesson's module "toy_lesson_pipeline:PIPELINE"
    sys.path.insert(0, str(FIXTURES))


# --- helpers ---------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=4)
def png_claiming(width: int, height: int) -> bytes:
    """A valid grey PNG of ``width`` x ``height`` zero pixels (never held decoded): one block of rows is
    deflated once and its bytes repeated (a full flush makes each copy stand alone), the checksum summed over
    the blocks; made once per size."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    row = b"\x00" * (width + 1)  # filter byte + pixels
    per_block = max(1, min(height, (16 << 20) // len(row)))
    blocks, rest = divmod(height, per_block)

    def deflated(rows: int, mode: int) -> bytes:
        compressor = zlib.compressobj(9, zlib.DEFLATED, -15)  # raw deflate: the zlib frame is added below
        return compressor.compress(row * rows) + compressor.flush(mode)

    block = deflated(per_block, zlib.Z_FULL_FLUSH)
    checksum = 1
    for _ in range(blocks):
        checksum = zlib.adler32(row * per_block, checksum)
    checksum = zlib.adler32(row * rest, checksum)
    data = b"\x78\xda" + block * blocks + deflated(rest, zlib.Z_FINISH) + struct.pack(">I", checksum)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", data) + chunk(b"IEND", b""))


def jpeg_claiming(width: int, height: int) -> bytes:
    """A small real JPEG whose frame header is rewritten to claim ``width`` x ``height``."""
    ok, encoded = cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))
    data = bytearray(encoded.tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def png_of(pixels: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".png", pixels)
    assert ok
    return encoded.tobytes()


def _status_kib(key: str) -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise AssertionError(f"no {key} in /proc/self/status")


def memory_growth_mb(action: Callable[[], Any]) -> tuple[Any, float]:
    """``action()`` and how far the resident set grew over its start at its peak (VmHWM reset first), in MB."""
    try:
        with open("/proc/self/clear_refs", "w") as clear:
            clear.write("5")  # reset the peak resident set (VmHWM) to the current one
    except OSError:  # pragma: no cover - a kernel without it: the end is measured instead of the peak
        pass
    before = _status_kib("VmRSS")
    result = action()
    peak = max(_status_kib("VmHWM"), _status_kib("VmRSS"))
    return result, (peak - before) / 1024


@pytest.fixture
def roomy_client():
    """The toy app with a 32 MiB upload limit and room for large images in its sessions."""
    with make_client(SessionStore(max_sessions=8, max_bytes=2 * 1024 * MB), max_upload_bytes=32 * MB) as client:
        yield client


# --- pixels checked from the header -----------------------------------------------------------------
def test_a_30000_pixel_png_upload_is_refused_from_its_header_without_memory_growth(roomy_client):
    session_id = new_session(roomy_client)
    bomb = png_claiming(30000, 30000)
    assert len(bomb) < 1 * MB  # under a megabyte on the wire, 900 MP (2.7 GB as bytes, 10.8 GB as floats) decoded
    response, grown = memory_growth_mb(lambda: roomy_client.put(
        f"/api/sessions/{session_id}/values/images?filename=big.png", content=bomb,
        headers={"content-type": "image/png"}))
    body = assert_error(response, 413, "images", "capacity")
    assert "'big.png' is 30000 x 30000 pixels" in body["reason"] and "MAX_IMAGE_PIXELS" in body["reason"]
    assert grown < 200, f"the resident set grew by {grown:.0f} MB"
    # a multipart form and a JPEG claiming the same are refused the same way
    response, grown = memory_growth_mb(lambda: roomy_client.put(
        f"/api/sessions/{session_id}/values/images", files={"file": ("big.jpg", jpeg_claiming(30000, 30000),
                                                                    "image/jpeg")}))
    assert "'big.jpg' is 30000 x 30000" in assert_error(response, 413, "images", "capacity")["reason"]
    assert grown < 200, f"the resident set grew by {grown:.0f} MB"
    assert roomy_client.get(f"/api/sessions/{session_id}/values/images?format=npy&index=0").status_code == 200


def test_a_24_megapixel_photo_upload_passes(roomy_client):
    session_id = new_session(roomy_client)
    photo = png_of(np.full((4000, 6000), 128, np.uint8))  # a 24 MP camera's frame, grey
    response = roomy_client.put(f"/api/sessions/{session_id}/values/images?filename=camera.png", content=photo)
    assert response.status_code == 200, response.text
    assert response.json()["count"] == 1


def test_one_upload_of_many_images_is_bounded_in_total(roomy_client, monkeypatch):
    session_id = new_session(roomy_client)
    monkeypatch.setattr(budgets, "MAX_DATASET_PIXELS", 3 * 100 * 100)
    files = [("file", (f"v{i}.png", png_of(np.zeros((100, 100), np.uint8)), "image/png")) for i in range(4)]
    body = assert_error(roomy_client.put(f"/api/sessions/{session_id}/values/images", files=files), 413, "images",
                        "capacity")
    assert "MAX_DATASET_PIXELS" in body["reason"] and "append=true" in body["reason"]
    assert roomy_client.put(f"/api/sessions/{session_id}/values/images", files=files[:3]).status_code == 200


def test_an_upload_that_is_not_a_readable_image_names_the_formats(roomy_client):
    session_id = new_session(roomy_client)
    body = assert_error(roomy_client.put(f"/api/sessions/{session_id}/values/images?filename=x.png",
                                         content=b"\x89PNG\r\n\x1a\n truncated"), 422, "images", "invalid_value")
    assert "PNG, JPEG" in body["reason"]


def test_a_huge_file_in_a_folder_dataset_is_refused_by_name_without_decoding(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "a.png").write_bytes(png_of(np.zeros((48, 64), np.uint8)))
    (folder / "huge.png").write_bytes(png_claiming(30000, 30000))
    with pytest.raises(CapacityExceeded) as refused:
        read_images([str(folder / "a.png"), str(folder / "huge.png")])
    assert refused.value.field == "path" and "'huge.png'" in refused.value.reason
    with TestClient(create_app(SessionStore(data_root=tmp_path))) as client:
        assert client.get("/api/modules/calibration").status_code == 200  # imported before measuring
        response, grown = memory_growth_mb(lambda: client.post("/api/sessions", json={
            "module": "calibration", "dataset": "folder", "options": {"path": str(folder)}}))
    body = assert_error(response, 413, "options.path", "capacity")
    assert "'huge.png'" in body["reason"] and "30000 x 30000" in body["reason"]
    assert grown < 200, f"the resident set grew by {grown:.0f} MB"


# --- what dataset options may make -------------------------------------------------------------------
@pytest.mark.parametrize("module, options", [
    ("calibration", {"num_views": 15, "width": 4096, "height": 4096}),
    ("sfm", {"num_views": 30, "width": 2048, "height": 2048}),
])
def test_dataset_options_over_the_pixel_budget_are_refused_before_rendering(module, options):
    with TestClient(create_app(SessionStore())) as client:
        assert client.get(f"/api/modules/{module}").status_code == 200  # imported before measuring
        started = time.monotonic()
        response, grown = memory_growth_mb(lambda: client.post("/api/sessions", json={
            "module": module, "options": options}))
    body = assert_error(response, 413, "options.num_views", "capacity")
    assert "MAX_DATASET_PIXELS" in body["reason"] and f"{options['width']} x {options['height']}" in body["reason"]
    assert time.monotonic() - started < 10 and grown < 200


def test_the_dataset_budget_lets_the_defaults_and_real_sizes_through():
    budgets.check_dataset_pixels(views=15, width=640, height=480)
    budgets.check_dataset_pixels(views=15, width=2048, height=2048)
    budgets.check_image_pixels(6000, 4000, field="f", what="a 24 MP photo")
    with pytest.raises(CapacityExceeded):
        budgets.check_image_pixels(30000, 30000, field="f", what="x")


# --- the size of JSON answers -------------------------------------------------------------------------
def test_json_of_a_large_image_is_refused_and_points_to_npy_and_png(roomy_client):
    session_id = new_session(roomy_client)
    upload = png_of(np.zeros((4000, 4000), np.uint8))
    assert len(upload) < 100_000
    assert roomy_client.put(f"/api/sessions/{session_id}/values/images?filename=big.png",
                            content=upload).status_code == 200
    url = f"/api/sessions/{session_id}/values/images"
    response, grown = memory_growth_mb(lambda: roomy_client.get(url, params={"format": "json"}))
    body = assert_error(response, 422, "format", "invalid_value")
    assert "16000000 numbers" in body["reason"] and "format=npy" in body["reason"] and "png" in body["reason"]
    assert grown < 200, f"the resident set grew by {grown:.0f} MB"
    assert_error(roomy_client.get(url, params={"format": "json", "index": 0}), 422, "format")
    npy = roomy_client.get(url, params={"format": "npy", "index": 0})
    assert npy.status_code == 200 and np.load(io.BytesIO(npy.content)).shape == (4000, 4000)
    assert roomy_client.get(url, params={"format": "png", "index": 0}).status_code == 200


def test_the_json_budget_is_a_module_constant(roomy_client, monkeypatch):
    session_id = new_session(roomy_client)  # three 16 x 16 images: 768 numbers
    url = f"/api/sessions/{session_id}/values/images?format=json"
    assert roomy_client.get(url).status_code == 200
    monkeypatch.setattr(budgets, "MAX_JSON_NUMBERS", 500)
    assert "at most 500" in assert_error(roomy_client.get(url), 422, "format")["reason"]
    assert roomy_client.get(url + "&index=0").status_code == 200  # one view: 256 numbers


# --- nesting ------------------------------------------------------------------------------------------
def test_deeply_nested_json_is_a_4xx_never_a_500(store):
    deep = "[" * 90_000 + "]" * 90_000  # under the test app's 200 kB body limit
    with make_client(store, raise_server_exceptions=False) as client:
        session_id = new_session(client)
        upload = client.put(f"/api/sessions/{session_id}/values/images", content=deep,
                            headers={"content-type": "application/json"})
        assert "nests 90000 levels" in assert_error(upload, 422, "images", "invalid_value")["reason"]
        for url, body in [("/api/sessions", '{"module": "toy", "options": {"count": ' + deep + "}}"),
                          (f"/api/sessions/{session_id}/steps/add_noise", '{"sigma": ' + deep + "}"),
                          (f"/api/sessions/{session_id}/run-until/add_noise", '{"add_noise": ' + deep + "}")]:
            response = client.post(url, content=body, headers={"content-type": "application/json"})
            assert "nests arrays and objects too deeply" in assert_error(response, 400, "body", "bad_request")[
                "reason"], url


def test_nesting_within_the_limit_is_read_as_before(store):
    with make_client(store) as client:
        session_id = new_session(client)
        images = [[[0.5] * 4] * 4] * 2  # an image set as JSON: 3 levels of lists
        response = client.put(f"/api/sessions/{session_id}/values/images", json={"images": [
            {"pixels": image} for image in images]})
        assert response.status_code == 200, response.text


# --- submissions ----------------------------------------------------------------------------------------
def _lesson_service(tmp_path, **kwargs: Any) -> LessonService:
    def grade(submission):
        return {"score": 1.0, "tests": [], "output": "",
                "extra_data": {"lesson": submission.lesson, "max_score": 6.0, "seeds": {"clean": 987654321}}}

    return LessonService(catalog=LessonCatalog(LESSON_FIXTURES), poll_s=0.05, grade=grade,
                         queue=SubmissionQueue(f"sqlite:///{tmp_path / 'db.sqlite'}"), **kwargs)


def _submit(client, text: str):
    return client.post("/api/lessons/00-toy/submissions", files={"file": ("mine.py", text.encode(), "text/x-python")})


@pytest.mark.parametrize("source", ["x = " + "+".join(["1"] * 100_000) + "\n",  # RecursionError in the parser
                                    "x = " + "not " * 50_000 + "1\n",  # MemoryError in the parser
                                    "x = " + "(" * 10_000 + ")" * 10_000 + "\n"],  # too many parentheses
                         ids=["long-sum", "many-nots", "deep-parentheses"])
def test_a_submission_the_parser_cannot_handle_is_422(tmp_path, source):
    with TestClient(build_app(_lesson_service(tmp_path)), raise_server_exceptions=False) as client:
        body = assert_error(_submit(client, source), 422, "file", "invalid_value")
    assert body["reason"].startswith("mine.py")


def test_a_large_submission_parses_off_the_event_loop(tmp_path):
    service = _lesson_service(tmp_path)
    app = build_app(service)

    @app.get("/ping")
    async def ping() -> dict[str, str]:
        return {"pong": "yes"}

    source = "x = 1\n" * 40_000  # valid, and about a second of parsing

    async def scenario() -> dict[str, Any]:
        finished: dict[str, Any] = {}
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://lab") as client:
            async def timed(name: str, request) -> None:
                finished[name] = (await request).status_code, time.monotonic()

            submission = asyncio.create_task(timed("submit", client.post(
                "/api/lessons/00-toy/submissions", files={"file": ("mine.py", source.encode())})))
            await asyncio.sleep(0.05)  # the upload is read and its parse has begun
            await timed("ping", client.get("/ping"))
            await submission
        return finished

    try:
        finished = asyncio.run(scenario())
    finally:
        service.stop()
    assert finished["submit"][0] == 202 and finished["ping"][0] == 200
    assert finished["ping"][1] < finished["submit"][1], "the ping waited for the parse"


# --- seeds stay with the instructor --------------------------------------------------------------------
def _graded(client) -> str:
    response = _submit(client, "def make_noisy():\n    pass\n")
    assert response.status_code == 202, response.text
    submission_id = response.json()["id"]
    deadline = time.monotonic() + 20
    while client.get(f"/api/submissions/{submission_id}").json()["status"] != "done":
        assert time.monotonic() < deadline, "not graded"
        time.sleep(0.05)
    return submission_id


def test_seeds_are_in_the_instructors_view_only(tmp_path):
    with TestClient(build_app(_lesson_service(tmp_path, instructor_token="s3cret"))) as client:
        submission_id = _graded(client)
        student = client.get(f"/api/submissions/{submission_id}").json()
        assert "seeds" not in student["results"]["extra_data"] and "987654321" not in str(student)
        assert student["results"]["extra_data"]["max_score"] == 6.0
        assert_error(client.get(f"/api/submissions/{submission_id}?view=instructor"), 403, "authorization",
                     "forbidden")
        instructor = client.get(f"/api/submissions/{submission_id}?view=instructor",
                                headers={"Authorization": "Bearer s3cret"}).json()
        assert instructor["results"]["extra_data"]["seeds"] == {"clean": 987654321}


def test_without_a_token_the_student_view_still_hides_the_seeds(tmp_path):
    with TestClient(build_app(_lesson_service(tmp_path))) as client:
        submission_id = _graded(client)
        assert "seeds" not in client.get(f"/api/submissions/{submission_id}").json()["results"]["extra_data"]
        assert "seeds" in client.get(f"/api/submissions/{submission_id}?view=instructor").json()["results"][
            "extra_data"]


# --- the data root ----------------------------------------------------------------------------------------
@pytest.fixture
def rooted(tmp_path):
    """``root/photos`` with a real image, a link inside the root and a link to ``outside/secret.png``."""
    root, outside = tmp_path / "root", tmp_path / "outside"
    (root / "photos").mkdir(parents=True)
    outside.mkdir()
    image = png_of(np.zeros((48, 64), np.uint8))
    (root / "photos" / "a.png").write_bytes(image)
    (root / "other.png").write_bytes(image)
    (outside / "secret.png").write_bytes(image)
    os.symlink(root / "other.png", root / "photos" / "b.png")
    return root, outside


def test_a_file_linking_outside_the_data_root_is_refused_by_name(rooted):
    root, outside = rooted
    os.symlink(outside / "secret.png", root / "photos" / "c.png")
    with TestClient(create_app(SessionStore(data_root=root))) as client:
        response = client.post("/api/sessions", json={"module": "calibration", "dataset": "folder",
                                                      "options": {"path": str(root / "photos")}})
    body = assert_error(response, 403, "options.path", "forbidden")
    assert "'c.png'" in body["reason"] and "symbolic link" in body["reason"]


def test_links_that_stay_inside_the_data_root_are_allowed(rooted):
    root, _ = rooted
    store = SessionStore(data_root=root)
    spec = PIPELINES["toy"].datasets[0]
    folder_spec = type(spec)(name="folder", loader=spec.loader, summary="", options=(), takes_path=True)
    store.check_path(folder_spec, {"path": str(root / "photos")})  # b.png links to root/other.png: fine
    os.symlink(root / "photos" / "loop", root / "photos" / "loop")
    with pytest.raises(Forbidden, match="'loop'"):
        store.check_path(folder_spec, {"path": str(root / "photos")})
