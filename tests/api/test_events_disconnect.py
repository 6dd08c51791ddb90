"""A client that hangs up in the middle of an event stream leaves no traceback in the server's log.

The lab is served by a real uvicorn server on 127.0.0.1 (in a thread, logging to the test's log
capture) and the client is a raw socket. A client that stops reading while a run's events pile up (a
small socket buffer on both ends, so the server's writes wait) and then hangs up is the case that
logged ~130 lines of ``anyio.BrokenResourceError`` (FastAPI's keep-alive task wrote into the stream the
response had left); a client that reads an event and hangs up while the stream is quiet is the plain
case. Both wait past the keep-alive interval (turned down to a fraction of a second) before looking at
the log.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Generator
from typing import Annotated

import fastapi.routing
import httpx
import numpy as np
import pytest
import uvicorn
from api_helpers import wait_until
from toy_pipeline import add_noise, gradients, mean_intensity

from lab.api import create_app
from lab.core import Pipeline, Progress, Range, SessionStore

#: Progress events the long step sends, and the length of each one's message: together far more than
#: the two small socket buffers and uvicorn's write buffer hold, so a client that stops reading stalls
#: the stream.
EVENTS, MESSAGE_CHARS, SOCKET_BUFFER = 120, 8000, 8192
#: The keep-alive interval for these tests (FastAPI's default is 15 s).
PING_SECONDS = 0.2

_HOLD = threading.Event()


def chatter(means: np.ndarray, *, iterations: Annotated[int, Range(1, EVENTS)] = EVENTS
            ) -> Generator[Progress, None, Annotated[np.ndarray, "chattered"]]:
    """Many long progress snapshots at once, then a wait for the test (the stream stays open)."""
    for i in range(iterations):
        yield Progress(iteration=i + 1, total=iterations, loss=1.0, message="x" * MESSAGE_CHARS)
    if not _HOLD.wait(timeout=30):
        raise RuntimeError("the test never let the step finish")
    return means


CHATTY = Pipeline.build(name="chatty", title="Chatty", summary="A step that streams many long events.",
                        steps=[add_noise, mean_intensity, chatter], datasets=[gradients])


@pytest.fixture
def served(monkeypatch) -> Generator[str, None, None]:
    """The API on a uvicorn server in a thread, its log records going to the test's capture; the URL."""
    monkeypatch.setattr(fastapi.routing, "_PING_INTERVAL", PING_SECONDS)
    _HOLD.clear()
    app = create_app(SessionStore(), modules={"chatty": CHATTY}.__getitem__, module_names=["chatty"],
                     viewer_url="http://127.0.0.1:9")
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER)  # accepted sockets inherit it
    listener.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_config=None, log_level="info"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    try:
        wait_until(lambda: server.started, "the server to start")
        yield f"http://127.0.0.1:{listener.getsockname()[1]}"
    finally:
        _HOLD.set()
        server.should_exit = True
        thread.join(timeout=20)
        listener.close()


def _open_stream(url: str, session_id: str) -> tuple[socket.socket, bytes]:
    """A raw client of the session's event stream with a small receive buffer, after its first event."""
    host, port = url.removeprefix("http://").split(":")
    client = socket.socket()
    client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
    client.settimeout(20)
    client.connect((host, int(port)))
    client.sendall(f"GET /api/sessions/{session_id}/events HTTP/1.1\r\nHost: {host}\r\n"
                   "Accept: text/event-stream\r\n\r\n".encode())
    received = b""
    while b"event: progress" not in received:
        chunk = client.recv(4096)
        assert chunk, "the stream ended before its first event"
        received += chunk
    return client, received


@pytest.mark.parametrize("client_kind", ["stalled", "reading"])
def test_a_client_that_hangs_up_mid_stream_leaves_no_traceback(served, client_kind, caplog):
    caplog.set_level(logging.INFO)
    caplog.set_level(logging.DEBUG, logger="lab.api.sessions")
    with httpx.Client(base_url=served, timeout=20) as api:
        sid = api.post("/api/sessions", json={"module": "chatty"}).json()["id"]
        assert api.post(f"/api/sessions/{sid}/run-until/mean_intensity", json={}).status_code == 200
        iterations = EVENTS if client_kind == "stalled" else 1
        started = api.post(f"/api/sessions/{sid}/steps/chatter", params={"wait": "false"},
                           json={"iterations": iterations})
        assert started.status_code == 202, started.text
        client, received = _open_stream(served, sid)
        assert b"200 OK" in received.split(b"\r\n", 1)[0]
        wait_until(lambda: api.get(f"/api/sessions/{sid}").json()["progress"]["iteration"] == iterations,
                   "every progress snapshot to be taken")
        time.sleep(10 * PING_SECONDS)  # the stream forwards what piled up (stalled) or sends keep-alives
        client.close()  # with unread data (stalled): the peer resets the connection
        time.sleep(10 * PING_SECONDS)  # past the keep-alive interval after the hang-up
        _HOLD.set()
        wait_until(lambda: api.get(f"/api/sessions/{sid}").json()["running"] is None, "the step to end")
        assert api.get(f"/api/sessions/{sid}").json()["steps"]["chatter"] == "done"
    log = caplog.text
    assert "Traceback" not in log and "BrokenResourceError" not in log, log[log.find("Traceback"):][:3000]
    errors = [record.getMessage() for record in caplog.records if record.levelno >= logging.ERROR]
    assert errors == []
    if client_kind == "stalled":  # the route saw the hang-up it was built for
        assert "hung up mid-stream" in log
