"""The REST API on the real calibration module: a synthetic board calibrated end to end, its values
in every format, photos from a folder or uploaded, and bad input refused with the field named."""

from __future__ import annotations

import io
from typing import Any, Generator

import cv2
import numpy as np
import pytest
import trimesh
from api_helpers import assert_error, parse_events, snapshot
from fastapi.testclient import TestClient

from lab.api import create_app
from lab.core import SessionStore

#: A small synthetic set that calibrates in well under a second: a 6 x 4 board seen 4 times at 320 x 240.
SMALL = {"columns": 6, "rows": 4, "num_views": 4, "width": 320, "height": 240,
         "fx": 175.0, "fy": 173.5, "cx": 159.0, "cy": 121.0}
STEPS = ["detect_corners", "estimate_homographies", "estimate_intrinsics", "estimate_extrinsics",
         "estimate_distortion", "refine_calibration", "undistort_image"]


@pytest.fixture(scope="module")
def client() -> Generator[TestClient, None, None]:
    store = SessionStore(max_sessions=16, max_bytes=2**28)
    with TestClient(create_app(store, module_names=["calibration"], max_upload_bytes=8 * 2**20)) as test_client:
        yield test_client


def _session(client: TestClient, **options: Any) -> str:
    response = client.post("/api/sessions", json={"module": "calibration", "options": {**SMALL, **options}})
    assert response.status_code == 201, response.text
    return response.json()["id"]


@pytest.fixture(scope="module")
def calibrated(client) -> tuple[str, dict[str, Any]]:
    sid = _session(client)
    response = client.post(f"/api/sessions/{sid}/run-until/refine_calibration",
                           json={"detect_corners": {"window": 4}})
    assert response.status_code == 200, response.text
    return sid, response.json()


def test_module_description_follows_the_contract(client):
    body = client.get("/api/modules/calibration").json()
    assert [s["name"] for s in body["steps"]] == STEPS
    detect = body["steps"][0]
    assert [i["name"] for i in detect["inputs"]] == ["images", "board"]
    window = detect["controls"]["properties"]["window"]
    assert (window["type"], window["minimum"], window["maximum"], window["default"]) == ("integer", 2, 15, 5)
    assert body["steps"][5]["long"] is True
    assert [(d["name"], d["takes_path"]) for d in body["datasets"]] == [("synthetic", False), ("folder", True)]
    uploadable = {u["name"]: u["type"] for u in body["uploadable"]}
    assert uploadable["images"] == "ImageSet" and uploadable["board"] == "Checkerboard" and uploadable["K"] == "ndarray"


def test_run_until_refinement_recovers_the_camera(client, calibrated):
    sid, body = calibrated
    assert [r["step"] for r in body["records"]] == STEPS[:6]
    assert all(r["status"] == "ok" for r in body["records"])
    assert body["records"][0]["params"] == {"subpixel": True, "window": 4}
    assert body["records"][0]["metrics"] == {"views_found": 4, "views_total": 4}
    refine = body["records"][-1]["metrics"]
    assert refine["rms_px"] < 1.0
    assert refine["fx_rel_error"] < 0.02 and refine["fy_rel_error"] < 0.02
    K = np.array(client.get(f"/api/sessions/{sid}/values/K").json())
    np.testing.assert_allclose(K[[0, 1, 0, 1], [0, 1, 2, 2]], [175.0, 173.5, 159.0, 121.0], rtol=0.03)
    summary = client.get(f"/api/sessions/{sid}").json()
    assert summary["steps"]["undistort_image"] == "ready" and summary["has_truth"] is True


def test_calibration_values_in_every_format(client, calibrated):
    sid, _ = calibrated
    url = f"/api/sessions/{sid}/values"
    cameras = client.get(f"{url}/cameras").json()
    assert cameras["type"] == "Cameras" and np.shape(cameras["K"]) == (4, 3, 3) and cameras["image"] == "images"
    one = client.get(f"{url}/cameras", params={"index": 2}).json()
    assert np.shape(one["R"]) == (1, 3, 3)
    rms = client.get(f"{url}/per_view_rms").json()
    assert rms["type"] == "Curve" and rms["kind"] == "bar" and len(rms["categories"]) == 4
    corners = client.get(f"{url}/corners", params={"index": 1}).json()
    assert corners["type"] == "Points2D" and len(corners["xy"]) == 24 and set(corners["view"]) == {1}
    homographies = np.load(io.BytesIO(client.get(f"{url}/homographies", params={"format": "npy"}).content))
    assert homographies.shape == (4, 3, 3)
    np.testing.assert_allclose(homographies[:, 2, 2], 1.0)
    png = client.get(f"{url}/images", params={"format": "png", "index": 3}).content
    assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED).shape[:2] == (240, 320)
    mesh = trimesh.load(io.BytesIO(client.get(f"{url}/board_mesh", params={"format": "ply"}).content),
                        file_type="ply", process=False)
    assert len(mesh.faces) > 0
    residuals = client.get(f"{url}/residuals").json()
    assert residuals["type"] == "Segments2D" and len(residuals["start"]) == 4 * 24
    assert_error(client.get(f"{url}/cameras", params={"format": "png"}), 422, "format")


def test_refinement_progress_is_streamed(client, calibrated):
    sid, _ = calibrated
    with client.stream("GET", f"/api/sessions/{sid}/events") as stream:
        events = list(parse_events(stream.iter_lines()))
    progress = [data for name, data in events if name == "progress"]
    assert progress and all(p["step"] == "refine_calibration" for p in progress)
    assert progress[-1]["loss"] <= progress[0]["loss"]
    assert events[-1][0] == "done" and events[-1][1]["records"][-1]["step"] == "refine_calibration"


@pytest.mark.parametrize("controls, field", [
    ({"window": 1}, "window"), ({"window": 16}, "window"), ({"window": "big"}, "window"),
    ({"subpixel": "perhaps"}, "subpixel"), ({"threshold": 3}, "threshold"),
])
def test_bad_detection_controls_are_422(client, controls, field):
    sid = _session(client)
    before = snapshot(client, sid)
    assert_error(client.post(f"/api/sessions/{sid}/steps/detect_corners", json=controls), 422, field, "invalid_control")
    assert snapshot(client, sid) == before


def test_homographies_before_corners_is_409(client):
    sid = _session(client)
    before = snapshot(client, sid)
    body = assert_error(client.post(f"/api/sessions/{sid}/steps/estimate_homographies"), 409, "corners",
                        "missing_input")
    assert "detect_corners" in body["reason"]
    assert snapshot(client, sid) == before


def test_undistort_view_out_of_range_is_422_and_keeps_the_state(client):
    sid = _session(client)
    client.post(f"/api/sessions/{sid}/run-until/refine_calibration")
    before = snapshot(client, sid)
    assert_error(client.post(f"/api/sessions/{sid}/steps/undistort_image", json={"view": 9}), 422, "view")
    after = snapshot(client, sid)
    assert after["values"] == before["values"] and after["steps"] == before["steps"]


@pytest.mark.parametrize("name, value, fragment", [
    ("K", np.eye(4).tolist(), "expected shape (3, 3)"),
    ("K", [[175.0, 0, 159], [3, 173.5, 121], [0, 0, 1]], "upper triangular"),
    ("K", [[175.0, 0, 159], [0, 173.5, 121], [0, 0, 0]], "K[2, 2] = 1"),
    ("dist", [0.1, 0.0, 0.0, 0.0], "expected shape (5,)"),
    ("homographies", np.eye(3).tolist(), "expected shape (N, 3, 3)"),
    ("board_points", [[0.0, 0.0]], "expected shape (N, 3)"),
])
def test_bad_uploads_of_calibration_values_are_422(client, calibrated, name, value, fragment):
    sid, _ = calibrated
    before = snapshot(client, sid)
    body = assert_error(client.put(f"/api/sessions/{sid}/values/{name}", json=value), 422, name, "invalid_value")
    assert fragment in body["reason"]
    assert snapshot(client, sid) == before


def test_upload_a_camera_matrix_then_undistort_with_it(client):
    sid = _session(client)
    client.post(f"/api/sessions/{sid}/run-until/refine_calibration")
    K = [[175.0, 0.0, 159.0], [0.0, 173.5, 121.0], [0.0, 0.0, 1.0]]
    body = client.put(f"/api/sessions/{sid}/values/K", json=K).json()
    assert body["shape"] == [3, 3] and body["invalidated"] == ["undistort_image"]
    record = client.post(f"/api/sessions/{sid}/steps/undistort_image", json={"view": 1, "alpha": 1.0}).json()
    assert record["status"] == "ok" and record["outputs"] == ["undistorted"]
    png = client.get(f"/api/sessions/{sid}/values/undistorted", params={"format": "png"}).content
    assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED).shape[:2] == (240, 320)


def test_upload_a_board_description(client):
    sid = _session(client)
    body = client.put(f"/api/sessions/{sid}/values/board", json={"columns": 6, "rows": 4, "square_size": 0.03}).json()
    assert body["type"] == "Checkerboard" and body["invalidated"][0] == "detect_corners"
    before = snapshot(client, sid)
    assert_error(client.put(f"/api/sessions/{sid}/values/board", json={"columns": 1, "rows": 4}), 422, "board.columns")
    assert_error(client.put(f"/api/sessions/{sid}/values/board", json={"cols": 6}), 422, "board")
    assert snapshot(client, sid) == before


@pytest.mark.parametrize("options, field", [
    ({}, "options.path"),
    ({"path": "/no/such/folder"}, "options.path"),
    ({"path": ".", "pattern": "../*.png"}, "options.pattern"),
    ({"path": ".", "columns": 1}, "options.columns"),
])
def test_folder_dataset_errors_name_the_option(client, options, field):
    count = client.get("/api/health").json()["sessions"]
    response = client.post("/api/sessions", json={"module": "calibration", "dataset": "folder", "options": options})
    assert_error(response, 422, field)
    assert client.get("/api/health").json()["sessions"] == count


def test_photos_from_a_folder_or_uploaded_calibrate(client, calibrated, tmp_path):
    sid, _ = calibrated
    photos = [client.get(f"/api/sessions/{sid}/values/images", params={"format": "png", "index": i}).content
              for i in range(4)]
    for i, png in enumerate(photos):
        (tmp_path / f"photo_{i}.png").write_bytes(png)
    (tmp_path / "notes.txt").write_text("not a photo")
    response = client.post("/api/sessions", json={"module": "calibration", "dataset": "folder",
                                                   "options": {"path": str(tmp_path), "columns": 6, "rows": 4}})
    assert response.status_code == 201, response.text
    folder = response.json()
    assert folder["has_truth"] is False and folder["dataset"] == "folder"
    record = client.post(f"/api/sessions/{folder['id']}/steps/detect_corners").json()
    assert record["metrics"] == {"views_found": 4, "views_total": 4}

    uploaded = _session(client, num_views=3)
    files = [("file", (f"photo_{i}.png", png, "image/png")) for i, png in enumerate(photos)]
    body = client.put(f"/api/sessions/{uploaded}/values/images", files=files).json()
    assert body["count"] == 4 and body["invalidated"][0] == "detect_corners"
    assert body["has_truth"] is False  # the synthetic truth does not describe uploaded photos
    records = client.post(f"/api/sessions/{uploaded}/run-until/refine_calibration").json()["records"]
    assert records[0]["metrics"] == {"views_found": 4, "views_total": 4}
    assert records[-1]["metrics"]["rms_px"] < 1.0
    assert "fx_rel_error" not in records[-1]["metrics"]
