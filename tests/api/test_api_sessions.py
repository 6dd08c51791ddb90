"""Sessions: create, read, reset, delete, and every way a create or a session id can be wrong."""

from __future__ import annotations


import pytest
from api_helpers import assert_error, make_client, new_session, snapshot
from toy_pipeline import add_noise, gradients

from lab.core.step import step_result, Warnings
from lab.api.sessions import viewer_link
from lab.core import ImageSet, Loaded, Pipeline


def folder(*, path: str) -> Loaded:
    """Photos from a folder (this one always fails, as a missing folder would)."""
    raise FileNotFoundError(f"no such folder: {path}")


@step_result
class Checked:
    checked: ImageSet
    warnings: Warnings = ()


def check(images: ImageSet) -> Checked:
    """Warn about the first image."""
    return Checked(images, tuple(f"{name} is dark" for name in images.names[:1]))


PHOTOS = Pipeline.build(name="photos", title="Photos", summary="", steps=[add_noise], datasets=[folder])
WARN = Pipeline.build(name="warn", title="Warn", summary="", steps=[check], datasets=[gradients])


def test_create_session_on_the_default_dataset(client, store):
    response = client.post("/api/sessions", json={"module": "toy"})
    assert response.status_code == 201
    body = response.json()
    assert response.headers["location"] == f"/api/sessions/{body['id']}"
    assert body["module"] == "toy" and body["dataset"] == "gradients" and body["seed"] == 0
    assert body["values"] == {"images": "ImageSet"}
    assert body["steps"] == {"add_noise": "ready", "mean_intensity": "blocked", "lift": "blocked"}
    assert body["history"] == [] and body["warnings"] == [] and body["has_truth"] is True
    assert body["running"] is None and body["progress"] is None
    assert body["viewer_url"] == "http://127.0.0.1:9999"
    assert body["links"]["viewer"] == f"http://127.0.0.1:9999/?session={body['id']}"
    assert body["id"] in store  # the shared store holds it, so the viewer sees it


def test_create_session_with_dataset_options_and_seed(client, store):
    response = client.post("/api/sessions", json={"module": "toy", "dataset": "gradients",
                                                   "options": {"count": 5, "size": 8}, "seed": 7})
    body = response.json()
    assert body["options"] == {"count": 5, "size": 8} and body["seed"] == 7
    images = store.get(body["id"]).get("images")
    assert len(images) == 5 and images[0].pixels.shape == (8, 8)


def test_read_session_reports_history_metrics_and_step_status(client):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/steps/add_noise", json={"sigma": 0.2})
    body = client.get(f"/api/sessions/{sid}").json()
    assert body["values"] == {"images": "ImageSet", "noisy": "ImageSet"}
    assert body["steps"]["add_noise"] == "done" and body["steps"]["mean_intensity"] == "ready"
    (record,) = body["history"]
    assert record["step"] == "add_noise" and record["status"] == "ok"
    assert record["params"] == {"sigma": 0.2, "mode": "gaussian"}
    assert record["seconds"] >= 0 and "mean_abs_change" in record["metrics"]
    assert body["metrics"]["add_noise"] == record["metrics"]
    assert body["version"] == 1


@pytest.mark.parametrize("body, status, field, kind", [
    ({"module": "nerf"}, 404, "module", "not_found"),
    ({"module": "toy", "dataset": "middlebury"}, 404, "dataset", "not_found"),
    ({"module": "toy", "options": {"count": 99}}, 422, "options.count", "invalid_control"),
    ({"module": "toy", "options": {"count": "many"}}, 422, "options.count", "invalid_control"),
    ({"module": "toy", "options": {"colour": "red"}}, 422, "options.colour", "invalid_control"),
    ({"module": "toy", "seed": -1}, 422, "seed", "invalid_request"),
    ({"module": "toy", "seed": "abc"}, 422, "seed", "invalid_request"),
    ({"module": "toy", "options": [1, 2]}, 422, "options", "invalid_request"),
    ({"module": "toy", "colour": "red"}, 422, "colour", "invalid_request"),
    ({"dataset": "gradients"}, 422, "module", "invalid_request"),
])
def test_bad_create_is_refused_naming_the_field(client, store, body, status, field, kind):
    assert_error(client.post("/api/sessions", json=body), status, field, kind)
    assert len(store) == 0


def test_malformed_json_create_is_422_with_the_reason(client, store):
    response = client.post("/api/sessions", content=b'{"module": "toy",', headers={"content-type": "application/json"})
    body = assert_error(response, 422, "body", "invalid_request")
    assert body["reason"].startswith("malformed JSON")
    response = client.post("/api/sessions", content=b"module=toy", headers={"content-type": "text/plain"})
    body = assert_error(response, 422, "body", "invalid_request")
    assert "Content-Type: application/json" in body["reason"]
    assert len(store) == 0


def test_dataset_loader_failure_names_the_option(store):
    with make_client(store, modules={"photos": PHOTOS}.__getitem__, module_names=["photos"]) as client:
        body = assert_error(client.post("/api/sessions", json={"module": "photos", "options": {"path": "/nope"}}),
                            422, "options.path", "invalid_value")
        assert "/nope" in body["reason"]
        assert_error(client.post("/api/sessions", json={"module": "photos"}), 422, "options.path")
        assert len(store) == 0


@pytest.mark.parametrize("method, path", [
    ("get", ""), ("delete", ""), ("post", "/reset"), ("post", "/steps/add_noise"), ("post", "/run-until/lift"),
    ("post", "/cancel"), ("get", "/events"), ("get", "/values/images"), ("put", "/values/images"),
])
def test_unknown_session_is_404_on_every_route(client, method, path):
    response = client.request(method, f"/api/sessions/0123456789ab{path}")
    body = assert_error(response, 404, "session", "not_found")
    assert "0123456789ab" in body["reason"]


def test_delete_session(client, store):
    sid = new_session(client)
    response = client.delete(f"/api/sessions/{sid}")
    assert response.status_code == 204 and response.content == b""
    assert sid not in store
    assert_error(client.get(f"/api/sessions/{sid}"), 404, "session")
    assert_error(client.delete(f"/api/sessions/{sid}"), 404, "session")


def test_reset_all_steps_keeps_the_dataset(client):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/run-until/mean_intensity")
    body = client.post(f"/api/sessions/{sid}/reset").json()
    assert body["values"] == {"images": "ImageSet"}
    assert body["steps"] == {"add_noise": "ready", "mean_intensity": "blocked", "lift": "blocked"}
    assert body["metrics"] == {}


def test_reset_one_step_forgets_it_and_what_follows(client):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/run-until/lift")
    body = client.post(f"/api/sessions/{sid}/reset", params={"step": "mean_intensity"}).json()
    assert set(body["values"]) == {"images", "noisy"}
    assert body["steps"] == {"add_noise": "done", "mean_intensity": "ready", "lift": "blocked"}
    assert list(body["metrics"]) == ["add_noise"]


def test_reset_unknown_step_is_404_and_changes_nothing(client):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/run-until/lift")
    before = snapshot(client, sid)
    body = assert_error(client.post(f"/api/sessions/{sid}/reset", params={"step": "fly"}), 404, "step", "not_found")
    assert "add_noise" in body["reason"]
    assert snapshot(client, sid) == before


def test_session_made_over_rest_is_the_store_object_the_viewer_uses(client, store):
    sid = new_session(client)
    session = store.get(sid)
    session.run("add_noise", {"sigma": 0.0})  # as the viewer would, in the same process
    body = client.get(f"/api/sessions/{sid}").json()
    assert body["steps"]["add_noise"] == "done"
    assert body["history"][0]["params"]["sigma"] == 0.0


def test_warnings_of_current_results_are_listed(store):
    with make_client(store, modules={"warn": WARN}.__getitem__, module_names=["warn"]) as client:
        sid = new_session(client, "warn")
        record = client.post(f"/api/sessions/{sid}/steps/check").json()
        assert record["warnings"] == ["g0 is dark"]
        assert client.get(f"/api/sessions/{sid}").json()["warnings"] == [{"step": "check", "message": "g0 is dark"}]
        client.post(f"/api/sessions/{sid}/reset")
        assert client.get(f"/api/sessions/{sid}").json()["warnings"] == []


@pytest.mark.parametrize("viewer_url, expected", [
    (None, None),
    (":8080", ":8080/?session=abc"),
    ("http://host:8080/", "http://host:8080/?session=abc"),
    ("http://host:8080/?x=1", "http://host:8080/?session=abc"),
])
def test_viewer_link(viewer_url, expected):
    assert viewer_link(viewer_url, session="abc") == expected


def listing(*, path: str) -> Loaded:
    """The images of a folder: one gradient per file in it."""
    import os

    return gradients(count=max(1, min(8, len(os.listdir(path)))), size=4)


LISTING = Pipeline.build(name="listing", title="Listing", summary="", steps=[add_noise], datasets=[listing])


def test_a_data_root_forbids_folders_outside_it(tmp_path):
    from lab.core import SessionStore

    inside = tmp_path / "data" / "class"
    inside.mkdir(parents=True)
    (inside / "a.png").write_bytes(b"")
    store = SessionStore(data_root=tmp_path / "data")
    with make_client(store, modules={"listing": LISTING}.__getitem__, module_names=["listing"]) as client:
        assert client.post("/api/sessions", json={"module": "listing", "options": {"path": str(inside)}}
                           ).status_code == 201
        for outside in ("/etc", str(tmp_path), str(inside / ".." / ".." / "..")):
            body = assert_error(client.post("/api/sessions", json={"module": "listing", "options": {"path": outside}}),
                                403, "options.path", "forbidden")
            assert "outside the folder this server reads data from" in body["reason"]
        assert len(store) == 1
