"""The service endpoints: health, modules, OpenAPI, the landing page, and JSON errors for bad routes and bugs."""

from __future__ import annotations

import dataclasses
import json

from api_helpers import PIPELINES, assert_error, make_client
from fastapi import APIRouter
from toy_pipeline import TOY

from lab.core import Pipeline


def test_health_reports_status_sessions_modules_and_viewer_url(client, store):
    body = client.get("/api/health").json()
    assert body["status"] == "ok"
    assert body["sessions"] == 0
    assert body["modules"] == ["toy", "gated"]
    assert body["viewer_url"] == "http://127.0.0.1:9999"
    assert client.app.state.viewer_url == "http://127.0.0.1:9999"
    client.post("/api/sessions", json={"module": "toy"})
    assert client.get("/api/health").json()["sessions"] == 1


def test_viewer_url_set_after_creation_shows_in_health(client):
    client.app.state.viewer_url = ":8080"
    assert client.get("/api/health").json()["viewer_url"] == ":8080"


def test_list_modules_gives_steps_and_datasets_in_order(client):
    modules = client.get("/api/modules").json()
    assert [m["name"] for m in modules] == ["toy", "gated"]
    toy = modules[0]
    assert toy["available"] is True
    assert toy["title"] == "Toy"
    assert [s["name"] for s in toy["steps"]] == ["add_noise", "mean_intensity", "lift"]
    assert [s["long"] for s in toy["steps"]] == [False, False, True]
    assert toy["datasets"] == [{"name": "gradients", "summary": "Horizontal gradient images; truth is each image's mean.",
                                "takes_path": False}]


def test_describe_module_has_control_schemas_outputs_metrics_and_dataset_options(client):
    body = client.get("/api/modules/toy").json()
    add_noise = body["steps"][0]
    assert add_noise["inputs"] == [{"name": "images", "type": "ImageSet", "optional": False}]
    sigma = add_noise["controls"]["properties"]["sigma"]
    assert sigma == {"type": "number", "minimum": 0.0, "maximum": 1.0, "default": 0.1, "title": "sigma",
                     "description": "standard deviation of the noise."}
    assert add_noise["controls"]["properties"]["mode"]["enum"] == ["gaussian", "uniform"]
    assert add_noise["controls"]["additionalProperties"] is False
    assert add_noise["outputs"] == [{"name": "noisy", "type": "ImageSet"}]
    assert add_noise["metrics"][0]["name"] == "mean_abs_change"
    assert body["steps"][2]["long"] is True
    options = body["datasets"][0]["options"]["properties"]
    assert options["count"] == {"type": "integer", "minimum": 1, "maximum": 8, "default": 3, "title": "count"}
    assert body["evaluated_steps"] == ["mean_intensity"]
    uploadable = {u["name"]: u for u in body["uploadable"]}
    assert set(uploadable) == {"images", "noisy", "means"}
    assert uploadable["means"] == {"name": "means", "type": "ndarray", "produced_by": "mean_intensity",
                                   "read_by": ["lift"]}


def test_unknown_module_is_404_naming_the_module(client):
    body = assert_error(client.get("/api/modules/nerf"), 404, "module", "not_found")
    assert "toy" in body["reason"]


def test_module_that_fails_to_load_is_listed_unavailable_and_503(store):
    def loader(name):
        if name == "broken":
            raise AttributeError("module 'lab.modules.broken' has no attribute 'PIPELINE'")
        return TOY

    with make_client(store, modules=loader, module_names=["toy", "broken"]) as client:
        listed = client.get("/api/modules").json()
        assert [m["available"] for m in listed] == [True, False]
        assert "PIPELINE" in listed[1]["reason"]
        assert_error(client.get("/api/modules/broken"), 503, "module", "unavailable")
        assert_error(client.post("/api/sessions", json={"module": "broken"}), 503, "module", "unavailable")
        assert len(store) == 0


def test_a_bug_is_a_json_500(store):
    @dataclasses.dataclass(frozen=True)
    class BuggyPipeline(Pipeline):
        def describe(self):
            raise RuntimeError("boom")

    buggy = BuggyPipeline(**{f.name: getattr(TOY, f.name) for f in dataclasses.fields(TOY)})
    with make_client(store, modules={"toy": buggy}.__getitem__, module_names=["toy"],
                     raise_server_exceptions=False) as client:
        body = assert_error(client.get("/api/modules/toy"), 500, "server", "internal")
        assert "RuntimeError: boom" in body["reason"]


def test_unknown_route_and_wrong_method_are_json(client):
    assert_error(client.get("/api/nothing-here"), 404, "path", "not_found")
    assert_error(client.delete("/api/modules"), 405, "path", "method_not_allowed")


def test_openapi_is_valid_json_listing_every_route_with_summaries(client):
    response = client.get("/openapi.json")
    assert response.status_code == 200
    spec = json.loads(response.text)
    assert spec["info"]["title"] == "Vision Lab"
    paths = spec["paths"]
    expected = {
        "/api/health": {"get"}, "/api/modules": {"get"}, "/api/modules/{module}": {"get"},
        "/api/sessions": {"post"}, "/api/sessions/{session_id}": {"get", "delete"},
        "/api/sessions/{session_id}/reset": {"post"}, "/api/sessions/{session_id}/steps/{step}": {"post"},
        "/api/sessions/{session_id}/run-until/{step}": {"post"}, "/api/sessions/{session_id}/cancel": {"post"},
        "/api/sessions/{session_id}/events": {"get"}, "/api/sessions/{session_id}/values/{name}": {"get", "put"},
    }
    for path, methods in expected.items():
        assert path in paths, path
        assert methods <= set(paths[path]), (path, set(paths[path]))
        for method in methods:
            assert paths[path][method]["summary"], (path, method)
    assert "/" not in paths
    assert "text/event-stream" in json.dumps(paths["/api/sessions/{session_id}/events"])
    assert "multipart/form-data" in paths["/api/sessions/{session_id}/values/{name}"]["put"]["requestBody"]["content"]
    run = paths["/api/sessions/{session_id}/steps/{step}"]["post"]["responses"]
    assert run["422"]["content"]["application/json"]["schema"] == {"$ref": "#/components/schemas/ErrorBody"}
    assert set(spec["components"]["schemas"]["ErrorBody"]["properties"]) == {"error", "field", "reason"}
    assert "HTTPValidationError" not in spec["components"]["schemas"]  # every error is documented as ErrorBody
    assert client.get("/docs").status_code == 200


def test_landing_page_is_served_and_fetches_the_api(client):
    response = client.get("/")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/html")
    page = response.text
    assert "<title>Vision Lab</title>" in page
    for needle in ('fetch("/api/lessons"', 'getJSON("/api/modules")', 'getJSON("/api/health")', 'href="/docs"'):
        assert needle in page
    assert client.get("/static/index.html").text == page


def test_extra_routers_are_included(store):
    router = APIRouter()

    @router.get("/api/lessons")
    def lessons():
        return [{"name": "zhang", "title": "Zhang's method", "module": "toy"}]

    with make_client(store, extra_routers=[router]) as client:
        assert client.get("/api/lessons").json()[0]["name"] == "zhang"


def test_default_catalog_serves_the_registered_modules(store):
    from lab.api import create_app
    from lab.modules import MODULES

    app = create_app(store)
    assert app.state.catalog.names == tuple(MODULES)
    assert set(PIPELINES) == {"toy", "gated"}
