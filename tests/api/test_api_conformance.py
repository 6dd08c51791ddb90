"""What the fuzzer (test_fuzz_api.py) found, pinned by direct tests: the API answers as its OpenAPI document says."""

from __future__ import annotations

from typing import Any

import pytest
from api_helpers import assert_error, new_session
from fastapi.testclient import TestClient

from lab.lessons.service import LessonService
from lab.lessons.store import SubmissionQueue


@pytest.fixture
def document(client: TestClient) -> dict[str, Any]:
    return client.get("/openapi.json").json()


@pytest.mark.parametrize(("path", "allowed"), [
    ("/api/sessions/abc", "GET, DELETE"),
    ("/api/sessions/abc/values/K", "GET, PUT"),
    ("/api/lessons/01-calibration/submissions", "GET, POST"),
    ("/api/sessions", "POST"),
])
def test_405_allow_names_every_method_of_the_path(client: TestClient, path: str, allowed: str) -> None:
    response = client.request("PATCH", path)
    assert_error(response, 405, "path", "method_not_allowed")
    assert response.headers["allow"] == allowed


@pytest.mark.parametrize("seed", [False, True, "3", 1.5, -1])
def test_seed_must_be_a_json_integer(client: TestClient, seed: Any) -> None:
    assert_error(client.post("/api/sessions", json={"module": "toy", "seed": seed}), 422, "seed", "invalid_request")


def test_seed_integer_is_kept(client: TestClient) -> None:
    assert client.post("/api/sessions", json={"module": "toy", "seed": 7}).json()["seed"] == 7


def test_json_body_that_is_not_utf8_is_a_documented_400(client: TestClient, document: dict[str, Any]) -> None:
    session_id = new_session(client)
    for path in ("/api/sessions", f"/api/sessions/{session_id}/steps/add_noise"):
        response = client.post(path, content=b"\xff\xfe{", headers={"content-type": "application/json"})
        assert_error(response, 400, "request", "bad_request")
    for path in ("/api/sessions", "/api/sessions/{session_id}/steps/{step}"):
        assert "400" in document["paths"][path]["post"]["responses"]


def test_error_bodies_are_documented_as_json_on_non_json_routes(document: dict[str, Any]) -> None:
    for path in ("/api/sessions/{session_id}/events", "/api/lessons/{lesson_id}/starter.py"):
        for status, response in document["paths"][path]["get"]["responses"].items():
            if status.startswith("4"):
                assert list(response["content"]) == ["application/json"], (path, status)


def test_starter_file_is_served_and_documented_as_python(client: TestClient, document: dict[str, Any],
                                                         tmp_path) -> None:
    client.app.state.lesson_service = LessonService(queue=SubmissionQueue(f"sqlite:///{tmp_path / 'db.sqlite'}"))
    try:
        response = client.get("/api/lessons/01-calibration/starter.py")
    finally:
        client.app.state.lesson_service.stop()
    assert response.status_code == 200
    assert response.headers["content-type"] == "text/x-python; charset=utf-8"
    assert list(document["paths"]["/api/lessons/{lesson_id}/starter.py"]["get"]["responses"]["200"]["content"]) == [
        "text/x-python"]


def test_submission_file_part_is_documented(document: dict[str, Any]) -> None:
    form = document["paths"]["/api/lessons/{lesson_id}/submissions"]["post"]["requestBody"]["content"]
    encoding = form["multipart/form-data"]["encoding"]["file"]
    assert encoding["contentType"] == "text/x-python"
    assert 'filename="solution.py"' in encoding["headers"]["Content-Disposition"]["schema"]["example"]


def test_links_lead_from_new_sessions_and_submissions(document: dict[str, Any]) -> None:
    paths = document["paths"]
    created = paths["/api/sessions"]["post"]["responses"]["201"]["links"]
    session_routes = [(m, p) for p, item in paths.items() if "{session_id}" in p for m in item]
    assert len(created) == len(session_routes) >= 9
    assert all(link["parameters"] == {"session_id": "$response.body#/id"} for link in created.values())
    submitted = paths["/api/lessons/{lesson_id}/submissions"]["post"]["responses"]["202"]["links"]
    assert {"submission_id": "$response.body#/id"} in [link["parameters"] for link in submitted.values()]
    listed = paths["/api/modules"]["get"]["responses"]["200"]["links"]
    assert [link["parameters"] for link in listed.values()] == [{"module": "$response.body#/0/name"}]
    operation_ids = {op["operationId"] for item in paths.values() for op in item.values()}
    assert all(link["operationId"] in operation_ids for path in paths.values() for op in path.values()
               for response in op["responses"].values() for link in response.get("links", {}).values())


def test_module_names_are_an_enum(document: dict[str, Any]) -> None:
    create = document["components"]["schemas"]["SessionCreate"]["properties"]["module"]
    assert create["enum"] == ["toy", "gated"]
    describe = document["paths"]["/api/modules/{module}"]["get"]["parameters"]
    assert [p["schema"].get("enum") for p in describe if p["name"] == "module"] == [["toy", "gated"]]
