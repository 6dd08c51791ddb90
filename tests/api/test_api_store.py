"""The session store's caps seen through the API: session count, memory, idle expiry; refusals, never eviction."""

from __future__ import annotations

import time
import types

import pytest
from api_helpers import assert_error, make_client, new_session, running_step, wait_until
from toy_pipeline import TOY

import lab.core.store
from lab.core import SessionStore


def _client(**store_options):
    return make_client(SessionStore(**{"max_sessions": 8, "idle_seconds": 3600.0, "max_bytes": 2**26,
                                       **store_options}))


def test_more_sessions_than_the_cap_is_503_with_retry_after_and_evicts_none():
    with _client(max_sessions=2) as client:
        first, second = new_session(client), new_session(client)
        response = client.post("/api/sessions", json={"module": "toy"})
        body = assert_error(response, 503, "sessions", "overloaded")
        assert "limit 2" in body["reason"] and int(response.headers["Retry-After"]) >= 1
        for sid in (first, second):
            assert client.get(f"/api/sessions/{sid}").status_code == 200
        assert client.get("/api/health").json()["sessions"] == 2
        client.delete(f"/api/sessions/{first}")
        new_session(client)  # a deleted session gives its place back


def test_no_room_when_every_session_is_busy_is_503(gate):
    with _client(max_sessions=1) as client:
        sid = new_session(client, "gated")
        client.post(f"/api/sessions/{sid}/run-until/mean_intensity")
        client.post(f"/api/sessions/{sid}/steps/crawl", params={"wait": "false"})
        wait_until(lambda: running_step(client, sid) == "crawl", "crawl to start")
        response = client.post("/api/sessions", json={"module": "toy"})
        body = assert_error(response, 503, "sessions", "overloaded")
        assert "limit 1" in body["reason"] and "every session is in use" in body["reason"]
        assert response.headers["Retry-After"] == "10"
        assert client.get("/api/health").json()["sessions"] == 1
        assert running_step(client, sid) == "crawl"  # the busy session was left alone
        gate.release(3)


def _toy_bytes() -> int:
    """Memory of a toy session on its default dataset, as the store counts it."""
    return SessionStore().create(TOY).nbytes()


def test_dataset_larger_than_the_memory_cap_is_413():
    with _client(max_bytes=10_000) as client:
        body = assert_error(client.post("/api/sessions", json={"module": "toy", "options": {"count": 8, "size": 64}}),
                            413, "dataset", "capacity")
        assert "MiB" in body["reason"]
        assert client.get("/api/health").json()["sessions"] == 0


def test_memory_cap_refuses_a_new_session_with_503_instead_of_evicting():
    size = _toy_bytes()
    with _client(max_bytes=int(2.5 * size)) as client:
        first, second = new_session(client), new_session(client)
        response = client.post("/api/sessions", json={"module": "toy"})
        body = assert_error(response, 503, "memory", "overloaded")
        assert "MiB" in body["reason"] and "Retry-After" in response.headers
        assert {client.get(f"/api/sessions/{sid}").status_code for sid in (first, second)} == {200}


def test_a_step_that_grows_a_session_past_the_memory_cap_evicts_nothing():
    size = _toy_bytes()
    with _client(max_bytes=int(3.5 * size)) as client:
        first, second = new_session(client), new_session(client)
        client.post(f"/api/sessions/{second}/steps/add_noise")  # second now holds images and noisy images
        assert client.get(f"/api/sessions/{first}").status_code == 200
        assert client.get(f"/api/sessions/{second}").json()["steps"]["add_noise"] == "done"
        assert_error(client.post("/api/sessions", json={"module": "toy"}), 503, "memory", "overloaded")
        client.post(f"/api/sessions/{second}/reset")  # freeing memory makes room again
        new_session(client)


def test_idle_sessions_expire(monkeypatch):
    with _client(idle_seconds=60.0) as client:
        old, recent = new_session(client), new_session(client)
        client.app.state.store.get(old).last_used -= 120.0
        body = assert_error(client.get(f"/api/sessions/{old}"), 404, "session", "not_found")
        assert body["reason"] == f"session {old!r} expired after 60 s idle and was dropped"
        assert client.get(f"/api/sessions/{recent}").status_code == 200
        later = time.time() + 3600.0
        monkeypatch.setattr(lab.core.store, "time", types.SimpleNamespace(time=lambda: later))
        assert_error(client.get(f"/api/sessions/{recent}"), 404, "session")
        assert client.get("/api/health").json()["sessions"] == 0


def test_a_running_session_does_not_expire(monkeypatch, gate):
    with _client(idle_seconds=60.0) as client:
        sid = new_session(client, "gated")
        client.post(f"/api/sessions/{sid}/run-until/mean_intensity")
        client.post(f"/api/sessions/{sid}/steps/crawl", params={"wait": "false"}, json={"iterations": 1})
        wait_until(lambda: running_step(client, sid) == "crawl", "crawl to start")
        later = time.time() + 3600.0
        monkeypatch.setattr(lab.core.store, "time", types.SimpleNamespace(time=lambda: later))
        assert client.get(f"/api/sessions/{sid}").json()["running"] == "crawl"
        gate.release()


@pytest.mark.parametrize("limit", [0, -5])
def test_create_app_refuses_a_nonpositive_upload_limit(limit):
    with pytest.raises(ValueError):
        make_client(SessionStore(), max_upload_bytes=limit)
