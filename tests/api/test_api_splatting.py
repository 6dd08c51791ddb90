"""The Gaussian splatting module over REST, on the real catalog: a tiny run, and bad input refused by name
(a control out of range, points asked for where the dataset has none, NaN points uploaded, more Gaussians
than the cap), while a camera looking away from every Gaussian renders the background (not an error)."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from api_helpers import assert_error
from fastapi.testclient import TestClient

from lab.api import create_app
from lab.core import Cameras, PointCloud, SessionStore
from lab.core.codecs import to_json

TINY = {"iterations": 8, "budget_seconds": 0.0, "densify_every": 0, "preview_every": 10}


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(SessionStore())) as client:
        yield client


def _session(client: TestClient, dataset: str = "synthetic_object", **options) -> str:
    response = client.post("/api/sessions", json={"module": "splatting", "dataset": dataset,
                                                  "options": {"train_views": 2, "test_views": 1, **options}})
    assert response.status_code == 201, response.text
    return response.json()["id"]


def _run(client: TestClient, sid: str, step: str, controls: dict | None = None):
    return client.post(f"/api/sessions/{sid}/steps/{step}", json=controls or {})


def test_splatting_is_listed_with_its_steps(client):
    body = client.get("/api/modules/splatting").json()
    assert [s["name"] for s in body["steps"]] == ["initialize_gaussians", "train_splats", "render_held_out",
                                                  "render_view", "render_path"]


def test_bad_controls_and_missing_points_are_named(client):
    sid = _session(client)
    assert_error(_run(client, sid, "initialize_gaussians", {"points": 2}), 422, "points")
    body = assert_error(_run(client, sid, "initialize_gaussians", {"source": "points"}), 422, "source")
    assert "brings no points" in body["reason"]


def test_nan_points_are_refused_on_upload(client):
    sid = _session(client)
    cloud = to_json(PointCloud(np.zeros((5, 3))))
    cloud["xyz"][2][1] = float("nan")
    response = client.put(f"/api/sessions/{sid}/values/sfm_points", content=json.dumps(cloud),  # NaN token
                          headers={"content-type": "application/json"})
    assert response.status_code == 422, response.text
    assert "sfm_points" in response.json()["field"] and "NaN" in response.json()["reason"]


def test_more_gaussians_than_the_cap_is_a_capacity_error(client, monkeypatch):
    monkeypatch.setattr("lab.modules.splatting.values.MAX_GAUSSIANS", 10)
    sid = _session(client)
    body = assert_error(_run(client, sid, "initialize_gaussians", {"points": 11}), 413, "points", "capacity")
    assert "more than the cap of 10" in body["reason"]


def test_a_camera_looking_away_renders_the_background_and_lists_no_gaussian(client):
    sid = _session(client, "object_with_points", points=200)
    for step, controls in (("initialize_gaussians", {"points": 100}), ("train_splats", TINY)):
        record = _run(client, sid, step, controls)
        assert record.status_code == 200 and record.json()["status"] == "ok", record.text
    test = Cameras(np.array([[[100.0, 0, 49.5], [0, 100.0, 49.5], [0, 0, 1]]]),
                   np.eye(3)[None], np.array([[0.0, 0.0, -3.0]]), 100, 100)
    # its centre -R^T t is (0, 0, 3), its axis R[2] is +z: it looks away from the object about the origin
    assert client.put(f"/api/sessions/{sid}/values/test_cameras", json=to_json(test)).status_code == 200
    record = _run(client, sid, "render_view", {"view": 0})
    assert record.status_code == 200, record.text
    assert record.json()["metrics"]["pixel_count"] == 0
    image = client.get(f"/api/sessions/{sid}/values/rendered", params={"format": "npy"})
    assert image.status_code == 200
    pixels = np.load(io.BytesIO(image.content))
    np.testing.assert_array_equal(pixels, np.ones((100, 100, 3), np.float32))
