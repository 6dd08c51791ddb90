"""The combined server: REST API and viewer in one process, on two loopback ports, sharing one store."""

from __future__ import annotations

import socket

import httpx
import pytest

from lab.core import SessionStore
from lab.server import start
from toy_pipeline import TOY


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def running():
    store = SessionStore(max_sessions=4)
    lab = start(host="127.0.0.1", port=free_port(), viewer_port=free_port(), store=store,
                modules={"toy": TOY})
    yield lab
    lab.stop()


def test_api_and_viewer_share_one_store(running):
    assert running.viewer.store is running.store
    with httpx.Client(base_url=running.api_url, timeout=30) as client:
        health = client.get("/api/health").json()
        assert health["status"] == "ok" and health["viewer_url"] == running.viewer_url
        assert health["modules"] == ["toy"]
        created = client.post("/api/sessions", json={"module": "toy", "options": {"count": 2}})
        assert created.status_code == 201, created.text
        session_id = created.json()["id"]
        session = running.store.get(session_id)  # the viewer can open it: same store
        version = session.version
        ran = client.post(f"/api/sessions/{session_id}/steps/add_noise", json={"sigma": 0.2})
        assert ran.status_code == 200, ran.text
        assert session.version > version and session.history[-1].params["sigma"] == 0.2


def test_viewer_serves_its_web_client(running):
    page = httpx.get(running.viewer_url + "/?session=abc", timeout=30)
    assert page.status_code == 200 and "<html" in page.text.lower()


def test_stop_frees_both_ports():
    lab = start(port=free_port(), viewer_port=free_port(), modules={"toy": TOY})
    api_port = int(lab.api_url.rsplit(":", 1)[1])
    viewer_port = lab.viewer.port
    lab.stop()
    for port in (api_port, viewer_port):
        with socket.socket() as sock:
            assert sock.connect_ex(("127.0.0.1", port)) != 0
